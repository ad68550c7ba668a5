"""The silhouette lift: a closed 3D Gaussian solid from one image and its object mask, no weights.

This is the stand-in for LGM when its weights are absent (README.md, "Where weights go": "no LGM →
silhouette lift"). The object is modelled as a solid symmetric about its mid-plane z = 0, inflated
from the silhouette the way sketch-based modelling tools inflate a drawn outline:

* Half-thickness. With d(p) the distance (pixels) from pixel p's centre to the silhouette edge,
  h(p) = thickness · sqrt(d (2R − d)) for d < R and thickness · R beyond. For a disk of radius r
  and R = r this is exactly a sphere; R = ``cap_fraction`` · max d (default 0.75) rounds the rim
  like a sphere of radius R and flattens the middle into a plateau, so a wide blob becomes a
  pillow about 0.75 of its half-width deep rather than a ball as deep as it is wide, while thin
  parts (handles, legs, d < R everywhere) stay round tubes.
* A ball. A round outline with a round bottom (``is_ball``) is lifted as deep as it is wide (R = max d,
  a sphere for a disc) with the principal point at its centre and no flat base, so that it rolls.
* Flat base. With ``on_ground`` the mask's lowest row is the contact with the ground, not a
  silhouette edge: the distance transform is taken on the mask mirrored below that row, so the
  solid keeps its full thickness down to the ground and stands on a flat base (an upright solid
  with a rounded bottom edge balances like a coin on its rim and topples).
* Camera. The input camera sits at (0, y_cam, D) looking down −z; with ``on_ground`` its
  principal point is shifted down to the object's base line, so the base is level (see
  ``silhouette_lift``). D first makes the mask's pixel height equal ``object_height`` metres at z = 0 (D = object_height · f / mask_height_px), then is
  refined by the few % that make the lifted solid itself exactly ``object_height`` tall; y_cam
  puts the lowest Gaussian on the ground plane when ``on_ground``.
* Surfaces. Each sampled pixel's front point lies on its own camera ray at z = +h, so the front
  surface re-projects exactly onto the pixels it came from. The back is the front's mirror image
  in the mid-plane z = 0, so the solid is symmetric and an upright object does not lean
  backwards by perspective. Rim Gaussians on the silhouette contour join each front point to its
  mirror along z (split into footprint-sized pieces where the segment is long, e.g. the flat
  base), closing the shell where front and back meet.
* Sampling. Front splats on a pixel grid of stride k, back splats on the same grid (stride 2k
  away from the outline when the budget is tight: the back is never seen from the input view),
  rim splats every k-th contour pixel. k is the smallest stride that keeps the total within
  ``max_gaussians`` (``choose_strides``); 1 when it fits.
* Gaussian shapes come from the surface's own Jacobian. A pixel-space footprint of σ =
  ``FOOTPRINT`` · stride pixels (across the outline: at most half the distance to it, so splats do
  not spill past the silhouette) is mapped onto the surface by ∂P/∂u, ∂P/∂v (P the surface point
  on the ray through (u, v)), plus a thin extent along the normal. So every splat projects to
  its intended footprint in the input view, while in 3D it stretches along the steep direction by
  sqrt(1 + |∇h|²) near the rim and the shell stays closed from the side.
* Colours: front and rim from the image (box-filtered over the sampling cell); back from a
  left-right mirror of the object taken within each image row's extent of the mask, blurred, so
  the back shows the object's own colours. With ``fit_colors`` the front colours are then solved
  so that rendering through the input camera reproduces the photo: overlapping splats mix each
  pixel with its neighbours in depth order (the nearer one wins), which costs ~5 dB if left alone.
  Rendering is linear in the colours, so one probe render with the differentiable rasterizer
  measures the blending weights and a sparse least-squares solve does the rest
  (``_solve_colors_linear``; ~2 s at 600x400 on a CPU). Gradient-descent steps (``fit_steps``) can
  follow, and are the fallback for a rasterizer without extra feature channels.
"""

from __future__ import annotations

import logging
import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np
import torch

from ..errors import InputError
from ..progress import ProgressFn, report
from ..segment.classic import as_image_array, as_mask_array
from ..types.camera import Camera
from ..types.gaussians import SH_C0, Gaussians, rotmat_to_quat

log = logging.getLogger(__name__)

FOOTPRINT = 0.6  # splat σ in units of the sampling stride (pixels): neighbours overlap and close
NORMAL_FRACTION = 0.2  # thickness of a splat along the surface normal, relative to its footprint
MAX_SLOPE = 40.0  # |∇h| cap: at the very rim the surface is vertical; keep splats bounded
RIM_SPREAD = 0.7  # rim splat σ along z, as a fraction of its piece's half-length
RIM_PIECE = 3.0  # a rim piece spans at most this many footprints along z (3:1 elongated splats)
MIN_MASK_PIXELS = 16

LAYER_FRONT, LAYER_BACK, LAYER_RIM = 0, 1, 2


@dataclass
class LiftResult:
    """What a lift produces.

    ``gaussians`` are in world space (metres, +y up); rendering them through ``camera`` reproduces
    the input foreground. ``layer`` (N,) int8 says which surface each Gaussian belongs to (0 front,
    1 back, 2 rim) and ``source_px`` (N, 2) int64 the (x, y) pixel it was sampled from.
    """

    gaussians: Gaussians
    camera: Camera
    mask: torch.Tensor
    layer: Optional[torch.Tensor] = None
    source_px: Optional[torch.Tensor] = None
    info: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------
# The inflation profile
# ----------------------------------------------------------------------------------------------


@dataclass
class InflationProfile:
    """Per-pixel half-thickness h (pixels) and its image gradient (∂h/∂u, ∂h/∂v)."""

    d: np.ndarray  # (H,W) distance from the pixel centre to the silhouette edge, px (0 outside)
    h: np.ndarray  # (H,W) half-thickness, px (0 outside)
    dh_du: np.ndarray  # (H,W)
    dh_dv: np.ndarray  # (H,W)
    R: float  # rounding radius (px)
    edge_u: np.ndarray  # (H,W) unit image-space direction into the object (∇d), u component
    edge_v: np.ndarray  # (H,W) v component


def exact_distance(m: np.ndarray) -> np.ndarray:
    """Euclidean distance (float64) from each non-zero pixel centre to the nearest zero pixel centre.

    OpenCV's precise transform finds the nearest zero pixel exactly, but its float32 values can
    differ in the last bit between calls (the first call in a process takes another code path).
    The squared distance is an integer, so rounding it restores the exact, reproducible value.
    """
    d = cv2.distanceTransform(m.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE).astype(np.float64)
    return np.sqrt(np.rint(d * d))


def inflation_profile(mask: np.ndarray, *, thickness: float = 1.0, cap_fraction: float = 0.75,
                      flat_base: bool = False) -> InflationProfile:
    """The rounded inflation of a binary mask (see the module docstring).

    The image border counts as silhouette edge (an object cut by the frame gets a rim there).
    d is measured from the pixel centre to the edge, i.e. the centre-to-centre distance transform
    minus half a pixel, so a boundary pixel has d = 0.5 and a small but non-zero thickness.

    ``flat_base``: the mask's lowest row is where the object stands on the ground, not an edge of
    its silhouette: distances are measured on the mask mirrored below that row, so the solid
    keeps its thickness down to the ground and stands on a flat base. Without it an upright
    object would balance on a rounded edge, like a coin on its rim, and (correctly) topple.
    """
    m = mask.astype(np.uint8)
    rows = np.nonzero(m.any(axis=1))[0]
    if flat_base and rows.size:
        base = int(rows.max()) + 1
        m = np.concatenate([m[:base], m[:base][::-1]], axis=0)
    m = np.pad(m, 1)
    H = mask.shape[0]
    d_in = exact_distance(m)[1:-1, 1:-1]
    d_out = exact_distance(1 - m)[1:-1, 1:-1]
    if d_in.shape[0] != H:  # drop the mirrored half (and pad the rows below the base back on)
        keep = min(H, d_in.shape[0])
        d_in = np.pad(d_in[:keep], ((0, H - keep), (0, 0)))
        d_out = np.pad(d_out[:keep], ((0, H - keep), (0, 0)), constant_values=1.0)
    inside = mask.astype(bool)
    d = np.where(inside, d_in - 0.5, 0.0).astype(np.float64)
    # A signed distance, smooth across the edge, gives the edge direction everywhere.
    signed = np.where(inside, d_in - 0.5, -(d_out - 0.5)).astype(np.float64)
    gv, gu = np.gradient(signed)
    R = max(0.5, float(cap_fraction) * float(d.max()))
    dd = np.clip(d, 1e-6, None)
    rounded = dd < R
    h = np.where(rounded, np.sqrt(np.clip(dd * (2.0 * R - dd), 0.0, None)), R) * thickness
    slope = np.where(rounded, (R - dd) / np.sqrt(np.clip(dd * (2.0 * R - dd), 1e-12, None)), 0.0) * thickness
    h = np.where(inside, h, 0.0)
    # On the medial axis ∇d cancels out (|∇d| < 1): that damps the slope on ridges, as it should.
    dh_du = np.where(inside, slope * gu, 0.0)
    dh_dv = np.where(inside, slope * gv, 0.0)
    norm = np.hypot(gu, gv)
    eu = np.where(norm > 1e-6, gu / np.maximum(norm, 1e-6), 1.0)
    ev = np.where(norm > 1e-6, gv / np.maximum(norm, 1e-6), 0.0)
    return InflationProfile(d=d, h=h, dh_du=dh_du, dh_dv=dh_dv, R=R, edge_u=eu, edge_v=ev)


# ----------------------------------------------------------------------------------------------
# Sampling
# ----------------------------------------------------------------------------------------------


def _grid(mask: np.ndarray, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of mask pixels on the stride grid (offset stride // 2, so a sparser grid of a
    multiple stride is a subset of a denser one)."""
    o = stride // 2
    ii, jj = np.nonzero(mask[o::stride, o::stride])
    return ii * stride + o, jj * stride + o


def _back_grid(mask: np.ndarray, kf: int, kb: int, d: np.ndarray):
    """The back's samples: the kb grid, plus the front's kf grid within 2·kb px of the outline
    (dense where the back curves round to meet the rim). Returns rows, cols, per-sample stride."""
    if kb == kf:
        r, c = _grid(mask, kf)
        return r, c, np.full(len(r), kf, np.int64)
    r, c = _grid(mask, kf)
    o = kf // 2
    on_coarse = ((r - o) % kb == 0) & ((c - o) % kb == 0)
    near = d[r, c] < 2.0 * kb
    keep = on_coarse | near
    return r[keep], c[keep], np.where(on_coarse[keep] & ~near[keep], kb, kf).astype(np.int64)


def _contours(mask: np.ndarray) -> list[np.ndarray]:
    """Boundary pixels of every outline (outer and holes), in order, as (n, 2) (x, y) arrays."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    return [c[:, 0, :] for c in contours]


def _contour_pixels(contours: list[np.ndarray], stride: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of every ``stride``-th boundary pixel along each contour."""
    pts = [c[::stride] for c in contours]
    if not pts:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    allp = np.concatenate(pts)
    return allp[:, 1].astype(np.int64), allp[:, 0].astype(np.int64)


def rim_piece_counts(h_px: np.ndarray, stride: int, f: float) -> np.ndarray:
    """How many splats ``_rim_splats`` puts on a contour pixel of half-thickness ``h_px``."""
    t_over_d = np.clip(1.0 - h_px / f, 1e-6, None)  # the front point's depth relative to D
    return np.clip(np.ceil(2.0 * h_px / (RIM_PIECE * FOOTPRINT * stride * t_over_d)), 1, 4096).astype(np.int64)


def choose_strides(mask: np.ndarray, max_gaussians: int, d: np.ndarray,
                   contours: Optional[list[np.ndarray]] = None, h: Optional[np.ndarray] = None,
                   f: float = 1e9) -> tuple[int, int]:
    """(front stride, back stride) in pixels so that front + back + rim <= max_gaussians.

    Stride 1 everywhere when it fits. Otherwise the back is sampled twice as sparsely as the
    front, except near the outline (it is never seen from the input view and its colours are
    blurred anyway); the front stride grows only when that is not enough.
    """
    if contours is None:
        contours = _contours(mask)
    n_px = int(mask.sum())
    k = max(1, int(math.sqrt(n_px / max(1, max_gaussians))))  # the front alone needs at least this
    while True:
        n_front = len(_grid(mask, k)[0])
        if h is None:
            n_rim = sum((len(c) + k - 1) // k for c in contours)
        else:
            rr, rc = _contour_pixels(contours, k)
            n_rim = int(rim_piece_counts(h[rr, rc], k, f).sum())
        for kb in (k, 2 * k):
            n_back = len(_back_grid(mask, k, kb, d)[0])
            if n_front + n_back + n_rim <= max_gaussians:
                return k, kb
        if n_front <= 1:
            raise InputError(f"max_gaussians={max_gaussians} is too small for this mask")
        k += 1


# ----------------------------------------------------------------------------------------------
# Colours
# ----------------------------------------------------------------------------------------------


def _extend_colors(img: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Fill the outside of the mask with nearby object colours (push-pull), for safe sampling."""
    levels = []
    col = img * mask[..., None]
    w = mask.astype(np.float32)
    while True:
        levels.append((col, w))
        if min(col.shape[:2]) <= 2 or w.min() > 0:
            break
        col = cv2.resize(col, (max(1, col.shape[1] // 2), max(1, col.shape[0] // 2)), interpolation=cv2.INTER_AREA)
        w = cv2.resize(w, (max(1, w.shape[1] // 2), max(1, w.shape[0] // 2)), interpolation=cv2.INTER_AREA)
        if col.ndim == 2:
            col = col[..., None]
    # Pull: from coarse to fine, fill where the weight is low with the upsampled coarser colour.
    col, w = levels[-1]
    filled = col / np.maximum(w[..., None], 1e-8)
    for col_l, w_l in reversed(levels[:-1]):
        up = cv2.resize(filled, (col_l.shape[1], col_l.shape[0]), interpolation=cv2.INTER_LINEAR)
        if up.ndim == 2:
            up = up[..., None]
        own = col_l / np.maximum(w_l[..., None], 1e-8)
        a = np.clip(w_l, 0.0, 1.0)[..., None]
        filled = a * own + (1.0 - a) * up
    return filled.astype(np.float32)


BACK_COLOR_MAX_SIDE = 512  # the back's colours are blurred: compute them at this size at most


def back_colors(img: np.ndarray, mask: np.ndarray, blur_fraction: float = 0.02) -> np.ndarray:
    """Colours for the back surface: each row of the object mirrored left-right within the mask's
    extent on that row, then blurred by ``blur_fraction`` of the object's size (a plausible,
    low-detail back made of the object's own colours). Full-size (H,W,3) result."""
    H, W = mask.shape
    scale = min(1.0, BACK_COLOR_MAX_SIDE / float(max(H, W)))
    if scale < 1.0:
        size = (max(2, int(round(W * scale))), max(2, int(round(H * scale))))
        small_img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        small_mask = cv2.resize(mask.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.5
        if not small_mask.any():  # a sliver that vanishes when shrunk: do it at full size
            small_img, small_mask, scale = img, mask.astype(bool), 1.0
    else:
        small_img, small_mask = img, mask.astype(bool)
    ext = _extend_colors(small_img, small_mask)
    out = ext.copy()
    for i in np.nonzero(small_mask.any(axis=1))[0]:
        cols = np.nonzero(small_mask[i])[0]
        a, b = int(cols[0]), int(cols[-1])
        out[i, a:b + 1] = ext[i, a:b + 1][::-1]
    ys, xs = np.nonzero(small_mask)
    blur_px = max(1.0, blur_fraction * max(np.ptp(ys) + 1, np.ptp(xs) + 1))
    mf = small_mask.astype(np.float32)
    blurred = cv2.GaussianBlur(out * mf[..., None], (0, 0), blur_px)
    weight = cv2.GaussianBlur(mf, (0, 0), blur_px)
    res = np.where(mf[..., None] > 0, blurred / np.maximum(weight[..., None], 1e-6), ext)
    if scale < 1.0:
        res = cv2.resize(res, (W, H), interpolation=cv2.INTER_LINEAR)
    return res.astype(np.float32)


# ----------------------------------------------------------------------------------------------
# Geometry
# ----------------------------------------------------------------------------------------------


def _rotscale_from_axes(A: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Columns of A (N,3,3) are σ-scaled axes of Σ = A Aᵀ; return unit wxyz quats and scales."""
    U, S, _ = torch.linalg.svd(A)
    det = torch.linalg.det(U)
    U = torch.cat([U[:, :, :2], U[:, :, 2:] * det[:, None, None].sign()], dim=2)
    return rotmat_to_quat(U), S


def _surface_splats(rows, cols, prof: InflationProfile, sign: float, stride, f: float, cx: float,
                    cy: float, D: float, s: float):
    """Means and σ-scaled axes (N,3,3) of one surface's splats (front sign=+1, back sign=-1).

    ``stride`` (scalar or per splat) is the sampling spacing in pixels. The splat is the image of a
    pixel-space footprint under the surface's Jacobian: σ = FOOTPRINT·stride along the outline,
    and across it no more than half the distance to the silhouette edge, so splats near the
    outline do not spill past it in the input view.
    """
    u = torch.as_tensor(cols, dtype=torch.float64) + 0.5
    v = torch.as_tensor(rows, dtype=torch.float64) + 0.5
    # A deterministic 1/1000-pixel depth pattern breaks exact depth ties (a flat plateau, a
    # symmetric outline), so every render sorts these splats the same way: the colour solve
    # measures the blending weights once and relies on them. Front and back share it (mirror).
    tie = ((np.asarray(rows) + 2 * np.asarray(cols)) % 5 - 2) * 1e-3
    h = torch.as_tensor(prof.h[rows, cols] + tie, dtype=torch.float64) * s  # metres
    gu = torch.as_tensor(prof.dh_du[rows, cols], dtype=torch.float64)
    gv = torch.as_tensor(prof.dh_dv[rows, cols], dtype=torch.float64)
    g = torch.hypot(gu, gv)
    shrink = torch.where(g > MAX_SLOPE, MAX_SLOPE / g.clamp_min(1e-12), torch.ones_like(g))
    gu, gv = gu * shrink, gv * shrink
    t = D - sign * h  # depth along the camera's viewing axis
    # The ray through (u, v), scaled so its depth component is 1: P = C + t * r.
    r = torch.stack([(u - cx) / f, -(v - cy) / f, -torch.ones_like(u)], dim=-1)
    means = torch.stack([r[:, 0] * t, r[:, 1] * t, D - t], dim=-1)
    # ∂P/∂u = t ∂r/∂u + r ∂t/∂u with ∂t/∂u = -sign * s * ∂h_px/∂u (and likewise for v).
    dr_du = torch.tensor([1.0 / f, 0.0, 0.0], dtype=torch.float64)
    dr_dv = torch.tensor([0.0, -1.0 / f, 0.0], dtype=torch.float64)
    Tu = t[:, None] * dr_du + r * (-sign * s * gu)[:, None]
    Tv = t[:, None] * dr_dv + r * (-sign * s * gv)[:, None]
    n = torch.linalg.cross(Tu, Tv)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    # Pixel-space footprint axes: across the outline (ê, the edge direction) and along it.
    eu = torch.as_tensor(prof.edge_u[rows, cols], dtype=torch.float64)
    ev = torch.as_tensor(prof.edge_v[rows, cols], dtype=torch.float64)
    d = torch.as_tensor(prof.d[rows, cols], dtype=torch.float64)
    foot = FOOTPRINT * torch.as_tensor(stride, dtype=torch.float64).expand_as(u)
    sigma_across = torch.minimum(foot, (d + 0.5) / 2.0)
    across = (eu[:, None] * Tu + ev[:, None] * Tv) * sigma_across[:, None]
    along = (-ev[:, None] * Tu + eu[:, None] * Tv) * foot[:, None]
    sigma_n = NORMAL_FRACTION * foot * t / f
    A = torch.stack([along, across, sigma_n[:, None] * n], dim=-1)
    return means, A


def _rim_splats(rows, cols, prof: InflationProfile, stride: int, f: float, cx: float, cy: float,
                D: float, s: float):
    """Splats closing the shell where the front meets its mirror image, the back.

    At each sampled contour pixel the front point F = (x, y, +h) (on the pixel's ray) and the back
    point B = (x, y, -h) are joined by a segment along z. Long segments (the flat base, where h
    is large) are split into pieces of at most RIM_PIECE footprints, so every splat stays
    small next to the simulation's particle spacing and deforms with its own neighbourhood.
    Returns means, σ-scaled axes and, per splat, the index of its contour pixel.
    """
    u = torch.as_tensor(cols, dtype=torch.float64) + 0.5
    v = torch.as_tensor(rows, dtype=torch.float64) + 0.5
    h = torch.as_tensor(prof.h[rows, cols], dtype=torch.float64) * s
    t = D - h
    r = torch.stack([(u - cx) / f, -(v - cy) / f, -torch.ones_like(u)], dim=-1)
    front = torch.stack([r[:, 0] * t, r[:, 1] * t, torch.zeros_like(u)], dim=-1)  # z set per piece
    eu = torch.as_tensor(prof.edge_u[rows, cols], dtype=torch.float64)
    ev = torch.as_tensor(prof.edge_v[rows, cols], dtype=torch.float64)
    tangent = torch.stack([-ev * t / f, -eu * t / f, torch.zeros_like(u)], dim=-1)  # (u,v)->(x,-y)
    foot = FOOTPRINT * stride
    n_pieces = torch.from_numpy(rim_piece_counts(prof.h[rows, cols], stride, f))
    owner = torch.repeat_interleave(torch.arange(len(u)), n_pieces)
    first = torch.cumsum(n_pieces, 0) - n_pieces
    k = torch.arange(len(owner)) - first[owner]  # index of each piece within its segment
    length = 2.0 * h[owner] / n_pieces[owner]
    z = -h[owner] + (k.double() + 0.5) * length
    means = front[owner].clone()
    means[:, 2] = z
    ez = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    along = RIM_SPREAD * 0.5 * length[:, None] * ez + 1e-9 * ez  # σ ≈ 0.35 of the piece length
    tan = foot * tangent[owner]
    normal = torch.linalg.cross(tan, ez.expand_as(tan))
    normal = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    A = torch.stack([tan, along, (NORMAL_FRACTION * foot * t[owner] / f)[:, None] * normal], dim=-1)
    return means, A, owner.numpy()


def _get_rasterizer():
    """The differentiable rasterizer, or None while the render stage is not installed."""
    try:
        from ..render import rasterize  # noqa: WPS433 (optional until the render stage exists)
    except ImportError:
        return None
    return rasterize


@dataclass
class _FitView:
    """The photo as the colour fit sees it: the mask's bounding box, averaged over q×q blocks."""

    camera: Camera  # renders exactly this crop at this resolution
    target: np.ndarray  # (h, w, 3)
    mask: np.ndarray  # (h, w) bool
    x0: int
    y0: int
    q: int


def _fit_view(camera: Camera, img: np.ndarray, m: np.ndarray, q: int, pad: int = 3) -> _FitView:
    """Crop to the mask (plus ``pad``) and average q×q blocks (q = 1: full resolution).

    With a sampling stride of k pixels there is one colour per k×k cell, so fitting at 1/q
    resolution (q ≈ k/2) loses nothing and keeps the probe render and the solve small on a 4k
    photo. Pixel centres stay consistent: block (i', j') is centred on full-resolution
    (x0 + q (j' + ½), y0 + q (i' + ½)), which the scaled camera below projects to (j' + ½, i' + ½).
    """
    H, W = m.shape
    ys, xs = np.nonzero(m)
    x0, y0 = max(0, int(xs.min()) - pad), max(0, int(ys.min()) - pad)
    x1, y1 = min(W, int(xs.max()) + 1 + pad), min(H, int(ys.max()) + 1 + pad)
    w, h = (x1 - x0) // q, (y1 - y0) // q  # whole blocks only (drops < q px at the far edges)
    w, h = max(1, w), max(1, h)
    blk = img[y0:y0 + h * q, x0:x0 + w * q]
    target = blk.reshape(h, q, w, q, 3).mean(axis=(1, 3)).astype(np.float32)
    mblk = m[y0:y0 + h * q, x0:x0 + w * q].astype(np.float32)
    mask = mblk.reshape(h, q, w, q).mean(axis=(1, 3)) > 0.5
    cam = Camera(width=w, height=h, fx=camera.fx / q, fy=camera.fy / q, cx=(camera.cx - x0) / q,
                 cy=(camera.cy - y0) / q, c2w=camera.c2w.clone(), near=camera.near, far=camera.far)
    return _FitView(cam, target, mask, x0, y0, q)


PROBE = 5  # splats are told apart by their grid position modulo PROBE: a PROBE² stencil


def _solve_colors_linear(rasterize, gaussians: Gaussians, front: torch.Tensor, grid_rc: np.ndarray,
                         stride: int, view: _FitView, cg_iters: int = 40, cg_tol: float = 1e-3,
                         damping: float = 1e-2):
    """Front colours that make the render match the photo inside the mask, from one probe render.

    A render is linear in the splat colours: rgb(p) = Σ_g w_g(p) c_g, the weights w set by the
    geometry, the opacities and the depth order. Rendering, as extra feature channels, a one-hot
    code of each front splat's grid position modulo PROBE (and the other splats' colours, which
    stay fixed) measures every weight of the PROBE×PROBE front splats around each pixel in a
    single pass. The colours then solve a sparse damped least-squares problem by conjugate
    gradients, without touching the rasterizer again. This matters because neighbouring splats
    overlap and the nearer one wins: the render is a depth-ordered mix of neighbours, not a
    symmetric blur that sharpening could undo.
    """
    n = len(gaussians)
    ga, gb = grid_rc[:, 0], grid_rc[:, 1]
    cls = torch.from_numpy(((ga % PROBE) * PROBE + gb % PROBE).astype(np.int64))
    feats = torch.zeros(n, PROBE * PROBE + 3)
    feats[front, cls] = 1.0
    others = torch.ones(n, dtype=torch.bool)
    others[front] = False
    feats[others, PROBE * PROBE:] = gaussians.rgb.detach().clamp(0, 1)[others]
    with torch.no_grad():
        out = rasterize(gaussians.detach(), view.camera, extra_features=feats)
    extra = getattr(out, "extra", None)
    h, w = view.mask.shape
    if extra is None or tuple(extra.shape) != (h, w, feats.shape[1]):
        raise NotImplementedError("the rasterizer did not return the extra feature channels")
    extra = extra.detach().float().cpu().numpy()
    # Which front splat sits at each grid point.
    o = stride // 2
    na, nb = int(ga.max()) + PROBE + 1, int(gb.max()) + PROBE + 1
    lut = np.full((na, nb), -1, np.int64)
    lut[ga, gb] = np.arange(len(ga))
    pi, pj = np.nonzero(view.mask)
    # The full-resolution pixel whose centre this (block) pixel is centred on, in grid units.
    a0 = np.rint((view.y0 + view.q * (pi + 0.5) - 0.5 - o) / stride).astype(np.int64)
    b0 = np.rint((view.x0 + view.q * (pj + 0.5) - 0.5 - o) / stride).astype(np.int64)
    # W as a dense stencil: for each pixel, PROBE² (splat index, weight) pairs; a missing splat
    # points at a dummy column n_front with weight 0. Gather/scatter beat general sparse products.
    n_pix, n_front = len(pi), len(ga)
    half = PROBE // 2
    idx_all = np.full((n_pix, PROBE * PROBE), n_front, np.int64)
    val_all = np.zeros((n_pix, PROBE * PROBE), np.float32)
    k = 0
    for da in range(-half, half + 1):
        for db in range(-half, half + 1):
            a, b = a0 + da, b0 + db
            ok = (a >= 0) & (b >= 0) & (a < na) & (b < nb)
            idx = np.full(n_pix, -1, np.int64)
            idx[ok] = lut[a[ok], b[ok]]
            cls_q = (a % PROBE) * PROBE + (b % PROBE)
            wgt = extra[pi, pj, cls_q]
            keep = idx >= 0
            idx_all[keep, k] = idx[keep]
            val_all[keep, k] = wgt[keep]
            k += 1
    # Row-compressed W (pixels × splats) for W·x; Wᵀ·y scatters. Both keep a fixed summation
    # order, so the result is reproducible.
    keep = idx_all < n_front
    counts = keep.sum(1)
    crow = torch.from_numpy(np.concatenate([[0], np.cumsum(counts)]).astype(np.int64))
    col = torch.from_numpy(idx_all[keep])
    val = torch.from_numpy(val_all[keep])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "sparse CSR support is in beta"
        w_csr = torch.sparse_csr_tensor(crow, col, val, (n_pix, n_front), check_invariants=False)
    rows_of = torch.from_numpy(np.repeat(np.arange(n_pix), counts))

    def apply_w(x):  # (n_front, 3) -> (n_pix, 3)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return w_csr @ x

    def apply_wt(y):  # (n_pix, 3) -> (n_front, 3)
        return torch.zeros(n_front, 3, dtype=y.dtype).index_add_(0, col, val[:, None] * y[rows_of])

    fixed = torch.from_numpy(extra[pi, pj, PROBE * PROBE:])
    tgt = torch.from_numpy(view.target[pi, pj]) - fixed
    c0 = gaussians.rgb.detach()[front].clamp(0, 1).float()

    def normal_op(x):
        return apply_wt(apply_w(x)) + damping * x

    # Preconditioned (Jacobi) conjugate gradients on (WᵀW + λI) c = Wᵀ t + λ c0, all three
    # channels at once; the damping keeps splats that barely show (hidden, or outside the fitted
    # pixels) at their photo colour.
    diag = torch.zeros(n_front).index_add_(0, col, val * val) + damping
    inv_diag = (1.0 / diag)[:, None]
    rhs = apply_wt(tgt) + damping * c0
    x = c0.clone()
    r = rhs - normal_op(x)
    z = inv_diag * r
    p = z.clone()
    rz = (r * z).sum(0)
    stop = (cg_tol ** 2) * (rhs * rhs).sum(0)
    for _ in range(int(cg_iters)):
        Ap = normal_op(p)
        alpha = rz / (p * Ap).sum(0).clamp_min(1e-20)
        x = x + alpha * p
        r = r - alpha * Ap
        if bool(((r * r).sum(0) <= stop).all()):
            break
        z = inv_diag * r
        rz_new = (r * z).sum(0)
        p = z + (rz_new / rz.clamp_min(1e-20)) * p
        rz = rz_new
    return x.clamp(0.0, 1.0)


def _fit_colors_adam(rasterize, gaussians: Gaussians, fit_index: torch.Tensor, view: _FitView,
                     steps: int, lr: float, time_budget: float, progress: Optional[ProgressFn]) -> int:
    """Gradient descent on the DC colours of ``fit_index`` (the generic, slower path)."""
    tgt = torch.from_numpy(view.target)
    m = torch.from_numpy(view.mask.astype(np.float32))[..., None]
    g = gaussians.detach()
    base = g.rgb.detach().clamp(0.0, 1.0)
    free = base[fit_index].clone().requires_grad_(True)
    opt = torch.optim.Adam([free], lr=lr)
    t0 = time.perf_counter()
    n_mask = float(m.sum()) * 3.0
    done = 0
    for step in range(steps):
        colors = base.index_put((fit_index,), free)
        out = rasterize(g, view.camera, colors=colors)
        loss = (((out.rgb - tgt) ** 2) * m).sum() / n_mask
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        with torch.no_grad():
            free.clamp_(0.0, 1.0)
        done = step + 1
        report(progress, done, steps)
        if time.perf_counter() - t0 > time_budget:
            break
    _set_rgb(gaussians, fit_index, free.detach())
    return done


def _set_rgb(gaussians: Gaussians, index: torch.Tensor, rgb: torch.Tensor) -> None:
    sh = gaussians.sh.detach().clone()
    sh[index, 0, :] = ((rgb - 0.5) / SH_C0).to(sh.dtype)
    gaussians.sh = sh


def _render_psnr(rasterize, gaussians: Gaussians, view: _FitView) -> float:
    with torch.no_grad():
        out = rasterize(gaussians.detach(), view.camera)
    m = torch.from_numpy(view.mask)
    err = ((out.rgb.detach().float().cpu() - torch.from_numpy(view.target)) ** 2)[m].mean()
    return float(10.0 * torch.log10(1.0 / err.clamp_min(1e-12)))


def _fit(gaussians: Gaussians, layer: torch.Tensor, grid_rc: np.ndarray, stride: int, camera: Camera,
         img: np.ndarray, m: np.ndarray, steps: int, lr: float, time_budget: float,
         progress: Optional[ProgressFn]) -> dict:
    rasterize = _get_rasterizer()
    if rasterize is None:
        log.warning("silhouette_lift: physmotion_core.render is not available; colours not fitted")
        return {"fit": "skipped: no rasterizer"}
    t0 = time.perf_counter()
    view = _fit_view(camera, img, m, q=max(1, stride // 2))
    front = torch.nonzero(layer == LAYER_FRONT)[:, 0]
    info: dict = {"fit_scale": 1.0 / view.q}
    try:
        rgb = _solve_colors_linear(rasterize, gaussians, front, grid_rc, stride, view)
        _set_rgb(gaussians, front, rgb)
        info["fit"] = "linear"
    except (TypeError, NotImplementedError) as exc:  # a rasterizer without extra feature channels
        log.info("silhouette_lift: linear colour solve unavailable (%s); using gradient descent", exc)
        steps = max(steps, 40)
        info["fit"] = "adam"
    report(progress, 1, 2)
    if steps > 0:
        visible = torch.nonzero(layer != LAYER_BACK)[:, 0]
        info["fit_steps"] = _fit_colors_adam(rasterize, gaussians, visible, view, steps, lr, time_budget,
                                             progress)
    info["fit_psnr"] = _render_psnr(rasterize, gaussians, view)
    info["fit_seconds"] = time.perf_counter() - t0
    report(progress, 2, 2)
    return info


# ----------------------------------------------------------------------------------------------
# The entry point
# ----------------------------------------------------------------------------------------------


CAP_FRACTION = 0.75  # the rounding radius over the deepest point's distance to the outline (a pillow)
BALL_ROUNDNESS = 0.85  # 4πA/P² of an outline read as a ball (a disc 1.0, an ellipse 2:1 0.84, a square 0.79)
BALL_BASE = 0.5  # ... whose width 5 % of its height above its lowest row is at most this share of its widest


def is_ball(mask: np.ndarray) -> bool:
    """Whether the silhouette lift reads the outline as a ball: one round outline (4πA/P² at least
    BALL_ROUNDNESS, P the outer contour's length) with a round bottom (its width 5 % of its height above its
    lowest row at most BALL_BASE of its widest: a disc 0.44, a dome cut flat at the bottom 1)."""
    m = (np.asarray(mask) > 0.5).astype(np.uint8)
    contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if len(contours) != 1 or len(contours[0]) < 16:
        return False
    area = float(m.sum())
    perimeter = float(cv2.arcLength(contours[0], True))
    if perimeter <= 0 or 4.0 * math.pi * area / perimeter**2 < BALL_ROUNDNESS:
        return False
    rows = np.nonzero(m.any(axis=1))[0]
    height = int(rows[-1] - rows[0] + 1)
    widths = m.sum(axis=1)
    near_base = int(rows[-1] - max(1, int(round(0.05 * height))))
    return float(widths[near_base]) <= BALL_BASE * float(widths.max())


def silhouette_lift(image, mask, *, object_height: float = 0.3, fov_y_deg: float = 40.0,
                    thickness: float = 1.0, max_gaussians: int = 60000, on_ground: bool = True,
                    ground_height: float = 0.0, fit_colors: bool = True, cap_fraction: Optional[float] = None,
                    flat_base: bool = True, ball: Optional[bool] = None,
                    opacity: float = 0.97, fit_steps: int = 0, fit_lr: float = 0.05,
                    fit_time_budget: float = 10.0, progress: Optional[ProgressFn] = None) -> LiftResult:
    """Lift the masked object of ``image`` (H,W,3) to a closed shell of 3D Gaussians.

    Returns world-space Gaussians (degree-0 SH) and the input camera through which they reproduce
    the photo. ``object_height`` is the object's real height in metres (it sets the physics' time
    scale); ``thickness`` scales the inflation depth; ``cap_fraction`` sets the rounding radius R
    as a fraction of the deepest point's distance to the outline. ``max_gaussians`` bounds the
    count (front, back and rim together; see ``choose_strides``). With ``on_ground`` the lowest
    Gaussian sits on y = ``ground_height``; otherwise the object is centred vertically on it.

    ``ball`` (None: from the outline, ``is_ball``): a round outline whose bottom is round too is lifted as a
    ball, not a pillow: ``cap_fraction`` 1 unless given (as deep as its outline is wide), no flat base, and
    the principal point at the outline's centre, so that its front and back shrink towards its centre by
    perspective and not towards its base. A pillow with the principal point on its base line is
    bottom-heavy (a weeble) and thinner than wide: a photographed ball thrown along the ground rolled back
    or fell over onto its face (docs/accuracy.md, "Rolling").
    """
    t_start = time.perf_counter()
    img = as_image_array(image)
    H, W = img.shape[:2]
    if mask is None:
        raise InputError("silhouette_lift needs the object mask (H, W); segment the image first")
    m = as_mask_array(mask, (H, W)) > 0.5
    n_px = int(m.sum())
    if n_px < MIN_MASK_PIXELS:
        raise InputError(f"The object mask has {n_px} pixels; the lift needs at least {MIN_MASK_PIXELS}. "
                         "Check the segmentation (the mask may be empty or the object tiny).")
    checks = {
        "object_height": (object_height, lambda x: math.isfinite(x) and x > 0,
                          "a positive number of metres (0.3 for a mug)"),
        "fov_y_deg": (fov_y_deg, lambda x: 1.0 < x < 170.0, "between 1 and 170 degrees"),
        "thickness": (thickness, lambda x: math.isfinite(x) and 0 < x <= 10, "in (0, 10] (1 = round)"),
        "cap_fraction": (cap_fraction, lambda x: math.isfinite(x) and 0 < x <= 1, "in (0, 1]"),
        "opacity": (opacity, lambda x: 0 < x <= 1, "in (0, 1]"),
        "ground_height": (ground_height, math.isfinite, "a finite height in metres"),
    }
    if ball is None:
        ball = is_ball(m)
    if cap_fraction is None:
        cap_fraction = 1.0 if ball else CAP_FRACTION
    checks["cap_fraction"] = (cap_fraction, lambda x: math.isfinite(x) and 0 < x <= 1, "in (0, 1]")
    for name, (value, ok, what) in checks.items():
        try:
            good = ok(float(value))
        except (TypeError, ValueError):
            good = False
        if not good:
            raise InputError(f"silhouette_lift: {name} must be {what}; got {value!r}")
    if int(max_gaussians) < 64:
        raise InputError(f"silhouette_lift: max_gaussians must be at least 64; got {max_gaussians}")

    prof = inflation_profile(m, thickness=float(thickness), cap_fraction=float(cap_fraction),
                             flat_base=bool(on_ground and flat_base and not ball))
    base_cam = Camera.from_fov(W, H, float(fov_y_deg))
    f, cx, cy = float(base_cam.fy), float(base_cam.cx), float(base_cam.cy)
    rows_any = np.nonzero(m.any(axis=1))[0]
    if on_ground:
        # Shift the principal point to the object's base line (a shift-lens view from the height
        # of the ground contact): rays through the lowest mask row are then horizontal, so the
        # front and the back of the base lie at the same height and the object stands level on a
        # flat base. With a centred principal point those rays slope downwards, the back of the
        # base hangs lower than its front, and the object would stand on its back edge and tip.
        cy = float(rows_any[-1] + 1)
    if ball:  # (the base is a point: nothing to keep level) its slices shrink towards its own centre
        ys, xs = np.nonzero(m)
        cx, cy = 0.5 * float(xs.min() + xs.max() + 1), 0.5 * float(ys.min() + ys.max() + 1)
    mask_height_px = int(rows_any[-1] - rows_any[0] + 1)
    D = float(object_height) * f / mask_height_px
    s = D / f  # metres per pixel on the mid-plane

    contours = _contours(m)
    kf, kb = choose_strides(m, int(max_gaussians), prof.d, contours, prof.h, f)
    fr, fc = _grid(m, kf)
    br, bc, bstride = _back_grid(m, kf, kb, prof.d)
    rr, rc = _contour_pixels(contours, kf)

    means_f, A_f = _surface_splats(fr, fc, prof, +1.0, kf, f, cx, cy, D, s)
    # The back is the mirror image of the front surface in the mid-plane z = 0 (computed at the
    # back's own samples): the solid is symmetric, so an upright object does not lean backwards
    # by perspective, and its base is level.
    means_b, A_b = _surface_splats(br, bc, prof, +1.0, bstride, f, cx, cy, D, s)
    means_b[:, 2] = -means_b[:, 2]
    A_b[:, 2, :] = -A_b[:, 2, :]
    means_r, A_r, rim_owner = _rim_splats(rr, rc, prof, kf, f, cx, cy, D, s)
    rr, rc = rr[rim_owner], rc[rim_owner]
    means = torch.cat([means_f, means_b, means_r])
    # Everything above is proportional to D (a similarity about the camera centre, which leaves
    # the image unchanged). The mid-plane rule makes the outline object_height tall at z = 0, but
    # the back bulges a few % past it by perspective: rescale so the solid itself (lowest to
    # highest Gaussian centre) is exactly object_height tall.
    ratio = float(object_height) / float(means[:, 1].max() - means[:, 1].min())
    D, s = D * ratio, s * ratio
    means = means * ratio
    quats, scales = _rotscale_from_axes(torch.cat([A_f, A_b, A_r]) * ratio)
    scales = scales.clamp_min(1e-12)

    # Colours: front and rim from the photo (averaged over the sampling cell); back mirrored.
    front_img = cv2.blur(img, (kf, kf)) if kf > 1 else img
    back_img = back_colors(img, m)
    col_f = front_img[fr, fc]
    col_b = back_img[br, bc]
    col_r = front_img[rr, rc]  # the rim is the outline seen in the photo
    rgb = torch.from_numpy(np.concatenate([col_f, col_b, col_r]).astype(np.float32))

    # Place the camera: the lowest point on the ground (or the object centred on that height).
    y_rel = means[:, 1]
    if on_ground:
        y_cam = float(ground_height) - float(y_rel.min())
    else:
        y_cam = float(ground_height) - 0.5 * float(y_rel.min() + y_rel.max())
    means[:, 1] += y_cam
    c2w = torch.eye(4)
    c2w[1, 3], c2w[2, 3] = y_cam, D
    camera = Camera(W, H, f, f, cx, cy, c2w)

    n = means.shape[0]
    gaussians = Gaussians.from_rgb(means.float(), rgb, scales.float(),
                                   torch.full((n,), float(opacity)), quats.float())
    layer = torch.cat([torch.full((len(fr),), LAYER_FRONT), torch.full((len(br),), LAYER_BACK),
                       torch.full((len(rr),), LAYER_RIM)]).to(torch.int8)
    source_px = torch.from_numpy(np.stack([np.concatenate([fc, bc, rc]), np.concatenate([fr, br, rr])], -1)
                                 .astype(np.int64))
    info = {"stride_front": kf, "stride_back": kb, "R_px": prof.R, "distance": D, "pixel_size": s,
            "n_front": len(fr), "n_back": len(br), "n_rim": len(rr), "y_cam": y_cam, "ball": bool(ball)}
    mask_t = torch.from_numpy(m.astype(np.float32))
    if fit_colors:
        info.update(_fit(gaussians, layer, np.stack([(fr - kf // 2) // kf, (fc - kf // 2) // kf], -1), kf,
                         camera, img, m, int(fit_steps), float(fit_lr), float(fit_time_budget), progress))
    info["seconds"] = time.perf_counter() - t_start
    gaussians.validate("silhouette_lift Gaussians")
    return LiftResult(gaussians=gaussians, camera=camera, mask=mask_t, layer=layer,
                      source_px=source_px, info=info)
