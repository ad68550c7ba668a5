"""Fit any Gaussians to the photo: the rotation, scale, position and focal length that make them
look like the masked object, then put them on the ground at the object's real height.

Lifts the pack did not make (TripoSplat, a .ply from any 3DGS tool, LGM, SAM 3D Objects) come in
their own canonical frame: any axis may be up, the input view may look along any axis, units and
centring are arbitrary. ``fit_gaussians_to_photo`` finds the similarity transform and the camera
through which the rendered silhouette and colours match the photo's masked object:

1. **Normalise.** Centre on the middle of the robust (2-98 %) extents of the significant
   (opacity >= 0.05) Gaussian centres and divide by the largest robust extent, so the object
   spans about one unit whatever its units.
2. **Coarse search** over the canonical frames: the 24 axis-aligned rotations (any input axis up,
   the input view along any of the 4 remaining axes), plus, with ``yaw_steps = 8``, the 24 in-between
   45° turns about the up axis. For each, the object is placed in front of the camera, rendered at
   low resolution (``COARSE_SIDE`` px, sized by the object's box) and its size, position and (for
   an elongated outline) turn about the viewing axis corrected from that render (area ratio,
   centroid and major axis of alpha vs the mask), then scored with the loss below. Levels below the
   finest render a spatially stratified subset of the Gaussians, as large as it takes to cover the
   object (``prep_for``: a sparse subset of a dense surface .ply is a sieve that ranks frames badly).
3. **Refinement** of the ``keep`` best candidates (a short run each; the best two finish the first
   level and the better one survives), then
   coarse-to-fine (``levels``): Adam on a rotation increment (axis-angle), the log of the object's
   on-screen size, its on-screen position and the log focal length (unless given), against
   ``(1 - soft IoU(alpha, mask)) + colour_weight · L1(colour, photo over the mask)``. When the
   result fails the checks below, a second round (``retry``) starts from the finalists turned 180°
   about the up axis and the next coarse candidates, and the better round is kept.
4. **Place**: a similarity about the camera centre leaves the image unchanged, so the fitted
   solution is scaled until the object (its significant Gaussian centres) is ``object_height``
   metres tall and shifted so its lowest centre is on the ground (y = 0) with its footprint
   centred on the y axis; the camera moves with it (level, looking down -z, OpenGL).

The result carries the hard IoU (alpha > 0.5 vs mask > 0.5 at the final fitting resolution); below
``iou_threshold`` it is marked as not lined up (``FitResult.ok``), with a message and an overlay
that shows where it went wrong. Hollow shells (a surface-only .ply) need nothing here: the
simulator fills the enclosed volume with particles (``sim/fill.py``).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..autograd import with_autograd
from ..errors import InputError
from ..progress import ProgressFn, report
from ..segment.classic import as_image_array, as_mask_array
from ..types.camera import Camera
from ..types.gaussians import Gaussians, rotmat_to_quat

log = logging.getLogger(__name__)

DEFAULT_FOV_Y = 40.0  # degrees; the silhouette lift's default, between a phone's main camera and a portrait lens
FOV_RANGE = (8.0, 110.0)  # the focal length is kept within these vertical fields of view (degrees)
DEFAULT_IOU_THRESHOLD = 0.85  # see docs/lift.md, "Fitting any Gaussians to the photo"
DEFAULT_MAX_COLOR_ERROR = 0.15  # ditto
SIGNIFICANT_OPACITY = 0.05
COARSE_SIDE = 32
# A coarse level renders a seeded random subset: about 2 Gaussians per pixel of the mask there (at
# least MIN_LEVEL_GAUSSIANS), doubled until the subset covers at least MIN_COVERAGE of what the
# finest level's set covers (``_coverage``). Per-pixel counts alone are not enough: a dense .ply of
# small surface splats (the stand-in of our templates: 20 000 splats of a cup, front, back and rim)
# rendered from a 1-per-pixel subset is a sieve (coverage 0.5-0.7 at 32 px), which made the size
# correction blow the object up and the colour term meaningless, so a wrong frame won the coarse
# search. The splats are NOT widened to make up for the ones left out: any widening (in 3D or on
# screen) fattens thin parts by a pixel or so, which at a coarse level is enough to prefer a wrong
# orientation of a thin bar.
MIN_LEVEL_GAUSSIANS = 600
MIN_COVERAGE = 0.95
MIN_MASK_PIXELS = 16
GRAD_CHUNK = 32
CONTENDER_MARGIN = 0.03
PLATEAU_STEPS = 5
PLATEAU_REL = 0.005
FINE_PER_PIXEL = 0.5
FINALISTS = 2  # contenders that finish the first level before one goes on
COLOUR_PICK_IOU_MARGIN = 0.15  # soft IoU below the best coarse candidate's that still counts as plausible
RETRY_MIN_ANGLE = 20.0  # degrees: a second-round start this close to one already tried is skipped


class FitError(InputError):
    """The Gaussians could not be lined up with the photo (IoU below the threshold).

    ``result`` is the best fit found (with its overlay), for a preview of what went wrong.
    """

    def __init__(self, message: str, result: "FitResult"):
        super().__init__(message)
        self.result = result


@dataclass
class FitResult:
    """What ``fit_gaussians_to_photo`` found.

    ``gaussians`` (world: metres, +y up, on the ground) and ``camera`` reproduce the photo;
    ``rotation`` (3,3), ``scale`` and ``translation`` (3,) are the similarity applied to the input
    (``x_world = scale · rotation @ x_in + translation``); ``view_rotation`` turns the input frame
    into the camera's (the pose the fit found; ``rotation`` = the camera's c2w rotation times it,
    see ``upright``); ``iou`` is the final hard IoU of the
    rendered silhouette with the mask, ``color_error`` the mean absolute colour difference (0..1)
    over the mask; ``overlay`` (H', W', 3) is the render over the photo beside the two silhouettes
    (mask green, render red, overlap yellow). ``ok`` is ``iou >= iou_threshold`` and, unless
    ``max_color_error`` is None or 0, ``color_error <= max_color_error``.
    """

    gaussians: Gaussians
    camera: Camera
    iou: float
    color_error: float
    rotation: torch.Tensor
    scale: float
    translation: torch.Tensor
    focal: float
    ok: bool
    iou_threshold: float
    max_color_error: Optional[float]
    overlay: torch.Tensor
    message: str
    seconds: float
    candidates: list = field(default_factory=list)
    info: dict = field(default_factory=dict)
    view_rotation: Optional[torch.Tensor] = None  # (3,3): the input frame turned into the camera's (OpenGL)

    def report(self) -> str:
        """A few lines for a node's STRING output / the log."""
        r = self.rotation.double()
        angle = math.degrees(math.acos(max(-1.0, min(1.0, (float(torch.trace(r)) - 1) / 2))))
        return (f"{self.message}\nIoU {self.iou:.3f} (threshold {self.iou_threshold:.2f}), colour error "
                f"{self.color_error:.3f}, focal {self.focal:.1f} px (fov_y {self.camera.fov_y_deg:.1f}°), "
                f"rotation {angle:.1f}° from the input frame, scale {self.scale:.4g} m per input unit, "
                f"{len(self.gaussians)} Gaussians, {self.seconds:.1f} s")

    def raise_if_failed(self) -> "FitResult":
        if not self.ok:
            raise FitError(self.message, self)
        return self


# ----------------------------------------------------------------------------------------------
# Rotations
# ----------------------------------------------------------------------------------------------


def _rot_y(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def canonical_rotations(yaw_steps: int = 8) -> torch.Tensor:
    """(6·yaw_steps, 3, 3) rotations: each input axis (±x, ±y, ±z) turned to +y (up), then turned
    about the up axis in ``yaw_steps`` equal steps. ``yaw_steps = 4`` gives the 24 rotations of
    the cube (every axis-aligned frame, y-up or z-up, input view along ±z or ±x); 8 adds the 45°
    turns in between."""
    if int(yaw_steps) < 1:
        raise InputError(f"yaw_steps must be at least 1; got {yaw_steps}")
    ups = []
    e = torch.eye(3)
    # A proper rotation taking input axis a to +y: rows of the matrix are the world axes in input
    # coordinates; pick x_w, z_w so that the frame is right-handed.
    for axis in range(3):
        for sign in (1.0, -1.0):
            up = sign * e[axis]
            side = e[(axis + 1) % 3]
            back = torch.linalg.cross(side, up)
            ups.append(torch.stack([side, up, back]))  # maps up -> +y, side -> +x
    out = []
    for R_up in ups:
        assert abs(float(torch.linalg.det(R_up)) - 1.0) < 1e-6
        for k in range(int(yaw_steps)):
            out.append(_rot_y(2 * math.pi * k / int(yaw_steps)) @ R_up)
    return torch.stack(out)


def upright_turn(R: torch.Tensor) -> torch.Tensor:
    """(3,3) float64: the smallest rotation that stands up the object whose input frame ``R`` turns into
    the camera's: the input axis nearest to the camera's up (±x, ±y or ±z; its up) is taken to the
    world's +y. It is the camera's c2w rotation when the object stands upright."""
    R = R.double()
    up_in = R[1]  # the camera's +y in input coordinates (Rᵀ e_y)
    k = int(torch.argmax(up_in.abs()))
    axis_in = torch.zeros(3, dtype=torch.float64)
    axis_in[k] = 1.0 if float(up_in[k]) >= 0 else -1.0
    u = R @ axis_in  # the object's up, in camera coordinates
    y = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    w = torch.linalg.cross(u, y)
    sin, cos = float(torch.linalg.vector_norm(w)), float(u @ y)
    if sin < 1e-12:
        return torch.eye(3, dtype=torch.float64)
    return axis_angle_to_matrix(w / sin * math.atan2(sin, cos))


def _skew(w: torch.Tensor) -> torch.Tensor:
    z = torch.zeros((), dtype=w.dtype)
    return torch.stack([torch.stack([z, -w[2], w[1]]), torch.stack([w[2], z, -w[0]]),
                        torch.stack([-w[1], w[0], z])])


def axis_angle_to_matrix(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula, differentiable everywhere (including w = 0)."""
    t2 = (w * w).sum()
    small = t2 < 1e-8
    t = torch.sqrt(torch.where(small, torch.ones_like(t2), t2))
    a = torch.where(small, 1.0 - t2 / 6.0, torch.sin(t) / t)
    b = torch.where(small, 0.5 - t2 / 24.0, (1.0 - torch.cos(t)) / torch.where(small, torch.ones_like(t2), t2))
    K = _skew(w)
    return torch.eye(3, dtype=w.dtype) + a * K + b * (K @ K)


def rotation_angle_deg(R: torch.Tensor) -> float:
    """Angle (degrees) of a rotation matrix."""
    c = (float(torch.trace(R.double())) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


# ----------------------------------------------------------------------------------------------
# Spherical harmonics under rotation (3DGS real SH basis, degrees 0-3)
# ----------------------------------------------------------------------------------------------

_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
       -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def _sh_basis(d: torch.Tensor, degree: int) -> torch.Tensor:
    """(M, (degree+1)²) real SH basis of unit directions d (M, 3), in 3DGS's order and signs."""
    x, y, z = d.unbind(-1)
    cols = [torch.full_like(x, 0.28209479177387814)]
    if degree >= 1:
        cols += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        cols += [_C2[0] * x * y, _C2[1] * y * z, _C2[2] * (2 * zz - xx - yy), _C2[3] * x * z, _C2[4] * (xx - yy)]
    if degree >= 3:
        cols += [_C3[0] * y * (3 * xx - yy), _C3[1] * x * y * z, _C3[2] * y * (4 * zz - xx - yy),
                 _C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _C3[4] * x * (4 * zz - xx - yy),
                 _C3[5] * z * (xx - yy), _C3[6] * x * (xx - 3 * yy)]
    return torch.stack(cols, -1)


def rotate_sh(sh: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """SH coefficients (N, K, 3) of Gaussians rotated by R: the colour seen along direction d
    after the rotation is the colour seen along Rᵀd before it. Each band transforms on its own by
    a (2l+1)² matrix, found here by least squares on sample directions (exact up to round-off,
    since a band is closed under rotation). K must be 1, 4, 9 or 16 (degree 0-3)."""
    K = sh.shape[1]
    degree = int(round(math.sqrt(K))) - 1
    if (degree + 1) ** 2 != K or degree > 3:
        raise InputError(f"rotate_sh: {K} SH coefficients per channel is not degree 0-3 (1, 4, 9 or 16)")
    if degree == 0:
        return sh.clone()
    g = torch.Generator().manual_seed(0)
    d = F.normalize(torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1)
    Rd = R.to(torch.float64)
    Y = _sh_basis(d, degree)
    Yr = _sh_basis(d @ Rd, degree)  # rows: Rᵀ d_i
    out = sh.clone()
    for l in range(1, degree + 1):
        sl = slice(l * l, (l + 1) * (l + 1))
        # Y[:, sl] @ D = Yr[:, sl]  ->  new coefficients c' = D c.
        D = torch.linalg.lstsq(Y[:, sl], Yr[:, sl]).solution  # ((2l+1), (2l+1))
        out[:, sl, :] = torch.einsum("ij,njc->nic", D.to(sh.dtype), sh[:, sl, :])
    return out


# ----------------------------------------------------------------------------------------------
# Targets and the differentiable placement
# ----------------------------------------------------------------------------------------------


@dataclass
class _Level:
    """The photo at one working resolution."""

    width: int
    height: int
    kx: float  # this level's pixels per photo pixel, across
    ky: float  # ... and down
    mask: torch.Tensor  # (h, w) soft, area-averaged
    hard: torch.Tensor  # (h, w) bool, mask > 0.5
    target: torch.Tensor  # (h, w, 3) photo colours (premultiplied by the soft mask)
    inside: torch.Tensor  # (h, w) bool: pixels where colour is compared


def _level(img: torch.Tensor, m: torch.Tensor, side: int, object_side: float) -> _Level:
    """The photo scaled so that the object's box (geometric mean of its sides: ``object_side``
    photo px) is about ``side`` px, never above the photo's own size. Sizing by the object, not
    the photo, keeps a thin bar or a small object in a wide frame resolvable at the coarse levels;
    the rasterizer only works on tiles the object touches, so the empty rest costs little."""
    H, W = m.shape
    factor = min(1.0, float(side) / max(float(object_side), 1.0))
    w, h = max(8, int(round(W * factor))), max(8, int(round(H * factor)))
    if (w, h) == (W, H):
        ms, tg = m.clone(), img * m[..., None]
    else:
        ms = F.interpolate(m[None, None], size=(h, w), mode="area")[0, 0]
        tg = F.interpolate((img * m[..., None]).permute(2, 0, 1)[None], size=(h, w), mode="area")[0].permute(1, 2, 0)
    # Colour is compared well inside the object only, where the premultiplied photo is its colour.
    inside = ms > 0.99
    if int(inside.sum()) < 4:
        inside = ms > 0.5
    return _Level(width=w, height=h, kx=w / W, ky=h / H, mask=ms, hard=ms > 0.5, target=tg, inside=inside)


@dataclass
class _Prep:
    """The input Gaussians, normalised (centred, about one unit across), ready to render."""

    means: torch.Tensor  # (N, 3) normalised
    cov: torch.Tensor  # (N, 3, 3) normalised
    opacities: torch.Tensor
    rgb: torch.Tensor  # (N, 3) DC colour, clamped to 0..1
    significant: torch.Tensor  # (N,) bool


def _prep(g: Gaussians, centre: torch.Tensor, extent: float, index: Optional[torch.Tensor] = None) -> _Prep:
    if index is not None:
        g = g.subset(index)
    means = (g.means.double() - centre) / extent
    cov = g.covariance().double() / (extent * extent)
    return _Prep(means=means.float(), cov=cov.float(), opacities=g.opacities.float(),
                 rgb=g.rgb.float().clamp(0.0, 1.0), significant=g.opacities >= SIGNIFICANT_OPACITY)


def _subset(means: torch.Tensor, keep: int, opacities: torch.Tensor, seed: int) -> Optional[torch.Tensor]:
    """A seeded, spatially stratified subset of at most ``keep`` Gaussians (the significant ones
    when there are enough), sorted; None when all are kept.

    The centres are binned on a cubic grid whose cell size is chosen (by bisection) so that at most
    ``keep`` cells are occupied; one Gaussian per occupied cell (the first in a seeded random order)
    is taken, and the rest of the budget is filled in that random order. Spread evenly like this, a
    subset of a surface of small splats leaves far fewer holes than a plain random one of the same
    size (the stand-in cup's 20 000 splats at 32 px: coverage 0.93-0.96 from 2000 instead of
    0.86-0.92)."""
    n = int(means.shape[0])
    if n <= keep:
        return None
    gen = torch.Generator().manual_seed(int(seed))
    sig = torch.nonzero(opacities >= SIGNIFICANT_OPACITY)[:, 0]
    pool = sig if sig.numel() >= keep else torch.arange(n)
    order = pool[torch.randperm(pool.numel(), generator=gen)]
    pts = means[order].double()
    lo = pts.min(0).values
    span = float((pts.max(0).values - lo).max())
    positions = torch.arange(order.numel())

    def first_per_cell(h: float) -> torch.Tensor:
        cell = torch.floor((pts - lo) / h).long()
        k = int(cell.max()) + 1
        key = (cell[:, 0] * k + cell[:, 1]) * k + cell[:, 2]
        uniq, inv = torch.unique(key, return_inverse=True)
        return torch.full((uniq.numel(),), order.numel(), dtype=torch.long).scatter_reduce(
            0, inv, positions, reduce="amin")

    chosen = torch.zeros(order.numel(), dtype=torch.bool)
    if span > 0 and math.isfinite(span):
        fine, coarse = span / 4096.0, span * 1.01  # too many occupied cells / exactly one
        for _ in range(20):  # bisection on log(cell size)
            h = math.sqrt(fine * coarse)
            if first_per_cell(h).numel() > keep:
                fine = h
            else:
                coarse = h
        chosen[first_per_cell(coarse)] = True
    rest = torch.nonzero(~chosen)[:, 0][: keep - int(chosen.sum())]
    chosen[rest] = True
    return torch.sort(order[chosen]).values


class _Params:
    """The fit's free parameters, each in well-scaled units.

    rotation = exp(ω) · R0; on-screen size σ (photo pixels per normalised unit at the object's
    centre); on-screen position (u, v) of the centre (photo pixels, as fractions of the longer
    side); focal f (photo pixels). The object sits at depth D0 = 1: scaling the object and its
    distance together leaves the image unchanged, so s = σ·D0/f is the object's scale and the
    perspective strength is σ/f.
    """

    def __init__(self, R0: torch.Tensor, log_sigma: float, uv: Sequence[float], log_f: float, side: float):
        self.R0 = R0.float()
        self.omega = torch.zeros(3, requires_grad=True)
        self.log_sigma = torch.tensor(float(log_sigma), requires_grad=True)
        self.uv = torch.tensor([float(uv[0]) / side, float(uv[1]) / side], requires_grad=True)
        self.log_f = torch.tensor(float(log_f), requires_grad=True)
        self.side = float(side)

    def state(self) -> tuple:
        with torch.no_grad():
            return (self.R0.clone(), self.omega.clone(), self.log_sigma.clone(), self.uv.clone(), self.log_f.clone())

    def load_state(self, state: tuple) -> None:
        with torch.no_grad():
            self.R0 = state[0].clone()
            for t, v in zip((self.omega, self.log_sigma, self.uv, self.log_f), state[1:]):
                t.copy_(v)

    def clone(self) -> "_Params":
        with torch.no_grad():
            return _Params(self.rotation(), float(self.log_sigma), (float(self.uv[0]) * self.side,
                           float(self.uv[1]) * self.side), float(self.log_f), self.side)

    def rotation(self) -> torch.Tensor:
        return axis_angle_to_matrix(self.omega) @ self.R0

    def place(self, prep: _Prep, cx: float, cy: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Camera-frame means and covariances (camera at the origin looking down -z)."""
        R = self.rotation()
        f = torch.exp(self.log_f)
        s = torch.exp(self.log_sigma) / f  # D0 = 1
        u, v = self.uv[0] * self.side, self.uv[1] * self.side
        t = torch.stack([(u - cx) / f, -(v - cy) / f, -torch.ones((), dtype=f.dtype)])
        means = s * (prep.means @ R.T) + t
        cov = (s * s) * (R @ prep.cov @ R.T)
        return means, cov


def _render(prep: _Prep, p: _Params, lv: _Level, cx: float, cy: float, colors: bool = True):
    from ..render.rasterize import rasterize

    out = _render_compiled(prep, p, lv, cx, cy, colors)
    if out is not None:
        return out
    means, cov = p.place(prep, cx, cy)
    f = torch.exp(p.log_f)
    n = means.shape[0]
    g = Gaussians(means=means, quats=torch.zeros(n, 4).index_fill_(1, torch.tensor([0]), 1.0),
                  scales=torch.ones(n, 3), opacities=prep.opacities, sh=torch.zeros(n, 1, 3), covars=cov)
    fl = float(f.detach())
    cam = Camera(lv.width, lv.height, fl * lv.kx, fl * lv.ky, cx * lv.kx, cy * lv.ky, torch.eye(4), near=1e-3,
                 far=1e3)
    if f.requires_grad:
        # The rasterizer takes the focal as a number. Scaling camera-frame x and y by ρ (at fixed
        # z; covariances by diag(ρ, ρ, 1) on both sides) gives exactly the image of focal ρ·f, so
        # with ρ = f / f.detach() (= 1 in value) the focal's gradient flows through the means.
        ratio = f / f.detach()
        d = torch.stack([ratio, ratio, torch.ones((), dtype=ratio.dtype)])
        g = Gaussians(means=means * d, quats=g.quats, scales=g.scales, opacities=g.opacities, sh=g.sh,
                      covars=cov * d[:, None] * d[None, :])
    rgb = prep.rgb if colors else torch.zeros_like(prep.rgb)
    if torch.is_grad_enabled() and g.means.requires_grad and g.means.device.type == "cpu":
        # A refinement step without Warp: the PyTorch rasterizer (the only other CPU path with
        # gradients), its 8 px tiles walked GRAD_CHUNK splats at a time (twice that where a tile holds
        # 48 or more on average) instead of its default 16. The result is the same (each pixel still
        # stops at the splat that saturates it); the fit's renders are small and deep, so the per-chunk
        # cost (one autograd node each, recomputed in backward) dominated: 1.3-1.7x less time per step
        # (the stand-in cup at 73x49-243x162 px).
        from ..render.rasterize import _rasterize_with_torch

        per_tile = n * 64.0 / float(lv.width * lv.height)
        chunk = 2 * GRAD_CHUNK if per_tile >= 48 else GRAD_CHUNK
        return _rasterize_with_torch(g, cam, rgb, g.opacities, None, "z", 0.3, chunk=chunk)
    return rasterize(g, cam, colors=rgb)


def _render_compiled(prep: _Prep, p: _Params, lv: _Level, cx: float, cy: float, colors: bool = True):
    """Every render of the fit (colour and alpha, no depth), compiled (render/_warp_grad.py), with gradients
    w.r.t. the parameters where they are asked: the object's placement is one affine map of the normalised
    splats into the camera, x -> A x + b, so the projection takes A and b (12 numbers) and returns their
    gradient summed over the drawn splats, and the compositing's backward pass is hand-written. The tensor
    path placed every splat (N 3x3 products), projected them through some forty autograd nodes and composited
    in dense tensor blocks; the renders without gradients (ranking, alignment, the final IoU) went through
    ``rasterize`` after the same placement. The same images and gradients to float32 round-off
    (tests/test_fit.py). None where the compiled path is not available (then ``_render`` takes the others)."""
    from ..render import _warp_grad
    from ..render.rasterize import RenderOutput

    if not _warp_grad.usable(prep.means, prep.cov):
        return None
    R = p.rotation()
    f = torch.exp(p.log_f)
    s = torch.exp(p.log_sigma) / f  # D0 = 1
    u, v = p.uv[0] * p.side, p.uv[1] * p.side
    # OpenGL camera frame (what _Params.place gives) -> OpenCV (y and z flipped), and x, y scaled by
    # ρ = f / f.detach() (= 1 in value: the focal's gradient, see _render).
    ratio = f / f.detach()
    flip = torch.stack([ratio, -ratio, -torch.ones((), dtype=f.dtype)])
    A = (s * R) * flip[:, None]
    b = torch.stack([(u - cx) / f, -(v - cy) / f, -torch.ones((), dtype=f.dtype)]) * flip
    fl = float(f.detach())
    rgb = prep.rgb if colors else torch.zeros_like(prep.rgb)
    try:
        proj = _warp_grad.project_affine(prep.means, prep.cov, prep.opacities, A, b, fx=fl * lv.kx, fy=fl * lv.ky,
                                         cx=cx * lv.kx, cy=cy * lv.ky, width=lv.width, height=lv.height, near=1e-3,
                                         far=1e3, eps2d=0.3)
        if proj is None:
            return None
        img = _warp_grad.composite(proj, rgb.index_select(0, proj.index), lv.width, lv.height)
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - a failed compiled launch: the other paths for the rest of the process
        _warp_grad.mark_failed(exc)
        return None
    alpha = img[..., 3]
    if (A.requires_grad or b.requires_grad) and not alpha.requires_grad:
        # Nothing drawn: keep the (zero) image attached so backward() still works.
        img = img + 0.0 * (A.sum() + b.sum())
        alpha = img[..., 3]
    return RenderOutput(rgb=img[..., :3], alpha=alpha, depth=torch.zeros_like(alpha.detach()), backend="warp")


def _losses(out, lv: _Level, colour_weight: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    a = out.alpha.clamp(0.0, 1.0)
    inter = (a * lv.mask).sum()
    union = (a + lv.mask - a * lv.mask).sum().clamp_min(1e-6)
    soft_iou = inter / union
    col = (out.rgb - lv.target).abs()[lv.inside].mean()
    return (1.0 - soft_iou) + colour_weight * col, soft_iou, col


def _hard_iou(alpha: torch.Tensor, hard: torch.Tensor) -> float:
    r = alpha > 0.5
    union = int((r | hard).sum())
    return float(int((r & hard).sum()) / union) if union else 0.0


def _moments(w: torch.Tensor, xs: torch.Tensor, ys: torch.Tensor) -> tuple[torch.Tensor, float, float]:
    """Centroid (2,), orientation of the major axis (radians, image axes: x right, y down) and the
    ratio of the principal second moments (>= 1) of a weight image."""
    a = float(w.sum())
    c = torch.stack([(w * xs).sum() / a, (w * ys).sum() / a])
    dx, dy = xs - c[0], ys - c[1]
    mxx, myy, mxy = float((w * dx * dx).sum()) / a, float((w * dy * dy).sum()) / a, float((w * dx * dy).sum()) / a
    angle = 0.5 * math.atan2(2 * mxy, mxx - myy)
    tr, det = mxx + myy, mxx * myy - mxy * mxy
    disc = math.sqrt(max(tr * tr / 4 - det, 0.0))
    lo = max(tr / 2 - disc, 1e-12)
    return c, angle, (tr / 2 + disc) / lo


def _probe_rotations() -> list[torch.Tensor]:
    """Three views of the normalised object, along its input z, y and x axes: a subset has to
    cover the object from each of them (a flat shell seen from one side can hide gaps that show
    from another)."""
    along_y = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    return [torch.eye(3), _rot_y(math.pi / 2), along_y]


def _coverage(prep: _Prep, probes: Sequence["_Params"], ref_alpha: Sequence[torch.Tensor], lv: _Level,
              cx: float, cy: float) -> float:
    """The worst, over the probe views, of the subset's alpha summed over the pixels that the
    reference set covers (alpha > 0.5) divided by the reference's own alpha there: 1 = no holes."""
    worst = 1.0
    with torch.no_grad():
        for q, a_ref in zip(probes, ref_alpha):
            inside = a_ref > 0.5
            if int(inside.sum()) == 0:
                continue
            a = _render(prep, q, lv, cx, cy, colors=False).alpha.clamp(0, 1)
            worst = min(worst, float(a[inside].sum() / a_ref[inside].sum()))
    return worst


ROLL_MIN_ELONGATION = 1.5  # both silhouettes must be at least this elongated (moment ratio) to align their axes


def _align(prep: _Prep, p: _Params, lv: _Level, cx: float, cy: float, m_area: float,
           m_centroid: torch.Tensor, m_angle: float, m_elong: float, roll: bool = True) -> None:
    """Correct a candidate from its own render: size (area ratio), position (centroid) and, for an
    elongated outline, the turn about the viewing axis that lines its major axis up with the
    mask's (a thin bar tilted in the picture plane otherwise scores badly in every frame), after
    which size and position are measured again (the turned outline's differ: a bar frame 6° off
    the truth, turned 13°, was left 20 % short, soft IoU 0.73 instead of 0.82)."""
    with torch.no_grad():
        out = _render(prep, p, lv, cx, cy, colors=False)
        a = out.alpha.clamp(0, 1)
        area = float(a.sum())
        if area < 1e-3:
            p.log_sigma += math.log(2.0)
            return
        ys, xs = torch.meshgrid(torch.arange(lv.height) + 0.5, torch.arange(lv.width) + 0.5, indexing="ij")
        c, angle, elong = _moments(a, xs, ys)
        p.log_sigma += 0.5 * math.log(m_area / area)
        # Centroid offset (level pixels -> photo pixels -> fraction of the longer side).
        p.uv += (m_centroid - c) / torch.tensor([lv.kx, lv.ky]) / p.side
        if roll and elong >= ROLL_MIN_ELONGATION and m_elong >= ROLL_MIN_ELONGATION:
            turn = (m_angle - angle + math.pi / 2) % math.pi - math.pi / 2  # the smaller of the two turns
            # An image turn by +turn (y down) is a turn by -turn about the camera's z axis (y up).
            cz, sz = math.cos(-turn), math.sin(-turn)
            Rz = torch.tensor([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
            p.R0 = Rz @ p.R0
            if abs(turn) > math.radians(1.0):
                _align(prep, p, lv, cx, cy, m_area, m_centroid, m_angle, m_elong, roll=False)


# ----------------------------------------------------------------------------------------------
# The entry point
# ----------------------------------------------------------------------------------------------


class _Adam:
    """Adam (Kingma & Ba) on a few scalar parameters, as ``torch.optim.Adam`` computes it (same
    bias corrections and epsilon). The fit's parameters are seven numbers; torch's optimiser adds
    per-step overhead and, on its first use in a process, imports torch._dynamo (4-5 s on a 2-core
    machine), which this avoids."""

    def __init__(self, groups: list, betas: tuple = (0.9, 0.999), eps: float = 1e-8):
        self.param_groups = [dict(g) for g in groups]
        self.b1, self.b2 = betas
        self.eps = eps
        self.t = 0
        self.state = {id(p): (torch.zeros_like(p), torch.zeros_like(p)) for g in self.param_groups for p in g["params"]}

    def zero_grad(self, set_to_none: bool = True) -> None:
        for g in self.param_groups:
            for p in g["params"]:
                p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        self.t += 1
        bc1 = 1.0 - self.b1 ** self.t
        bc2 = math.sqrt(1.0 - self.b2 ** self.t)
        for g in self.param_groups:
            for p in g["params"]:
                if p.grad is None:
                    continue
                m, v = self.state[id(p)]
                m.mul_(self.b1).add_(p.grad, alpha=1.0 - self.b1)
                v.mul_(self.b2).addcmul_(p.grad, p.grad, value=1.0 - self.b2)
                p.addcdiv_(m, v.sqrt() / bc2 + self.eps, value=-g["lr"] / bc1)


def _check_number(name, value, ok, what) -> float:
    try:
        v = float(value)
        good = math.isfinite(v) and ok(v)
    except (TypeError, ValueError):
        good = False
    if not good:
        raise InputError(f"fit_gaussians_to_photo: {name} must be {what}; got {value!r}")
    return v


@with_autograd
def fit_gaussians_to_photo(
    gaussians: Gaussians, image, mask, *, object_height: float = 0.3, focal: Optional[float] = None,
    principal_point: Optional[Sequence[float]] = None, iou_threshold: float = DEFAULT_IOU_THRESHOLD,
    max_color_error: Optional[float] = DEFAULT_MAX_COLOR_ERROR, on_ground: bool = True,
    ground_height: float = 0.0, colour_weight: float = 0.5, yaw_steps: int = 8,
    keep: int = 3, levels: Sequence[tuple[int, int]] = ((48, 30), (96, 30), (160, 20)),
    screen_steps: int = 12, max_fit_gaussians: int = 20000, lr: float = 0.02, seed: int = 0,
    retry: bool = True, upright: bool = True, raise_on_failure: bool = False,
    progress: Optional[ProgressFn] = None,
) -> FitResult:
    """Line ``gaussians`` (any frame, any units) up with the masked object of ``image``.

    Args:
        gaussians: the lift to fit (its own frame; hollow shells are fine, see the module doc).
        image: the photo (H, W, 3) in 0..1 (or uint8), torch or numpy.
        mask: the object's mask (H, W), 1 on the object.
        object_height: the object's real height in metres (the fitted object is scaled to it).
        focal: the photo's focal length in pixels (fx = fy); None = fitted, starting from a
            40° vertical field of view.
        principal_point: (cx, cy) in pixels; None = the image centre.
        iou_threshold: the fit counts as lined up when the final IoU reaches this (default 0.85).
        max_color_error: ... and the mean colour error over the mask (0..1) is at most this
            (default 0.15; None or 0 = not checked): an outline can match with the object turned
            the wrong way (a bar seen along another axis) or be another object's.
        on_ground: put the lowest significant Gaussian centre on ``ground_height`` (else centre
            the object on it).
        colour_weight: weight of the masked colour L1 against (1 - soft IoU).
        yaw_steps: turns about the up axis tried per up axis in the coarse search (4: the 24
            axis-aligned frames; 8: also the 45° turns between them).
        keep: coarse candidates refined before the best one is carried on.
        levels: (max image side in px, Adam steps) of each refinement level, coarse to fine; the
            candidates compete at the first level (``screen_steps`` steps each).
        max_fit_gaussians: at most this many Gaussians are rendered at the finest level (a
            seeded random subset, coarser levels fewer); the reported
            IoU uses all of them.
        lr: Adam learning rate (radians for the rotation, log units for size and focal).
        seed: seeds the subsets.
        retry: when the best fit fails the checks, refine a second round of starts (the next
            ``keep`` coarse candidates and the finalists turned 180° about the up axis) and keep
            the better round; a refused fit then takes about twice as long.
        upright: stand the object up in the world and tilt the camera instead. The fit finds the
            object's pose relative to the camera; a photo taken from above (or with a principal
            point off the centre) shows it tilted. The input axis nearest to the photo's up (±x,
            ±y or ±z of the .ply) is taken as the object's up and made the world's +y; the camera
            turns by what is left (its elevation and roll), so the render is the same. False puts
            the whole pose on the object under a level camera (a tilted object on flat ground
            topples when simulated).
        raise_on_failure: raise ``FitError`` (carrying the result) instead of returning a result
            with ``ok = False``.
        progress: ``progress(done, total)``, called every step (raise from it to cancel).
    """
    t_start = time.perf_counter()
    if not isinstance(gaussians, Gaussians):
        raise InputError(f"fit_gaussians_to_photo: gaussians must be Gaussians; got {type(gaussians).__name__}")
    g_in = gaussians.detach().to("cpu")
    g_in = Gaussians(**{k: (v.float() if torch.is_tensor(v) and v.is_floating_point() else v)
                        for k, v in g_in.__dict__.items()})
    g_in.validate("fit_gaussians_to_photo: gaussians")
    img_np = as_image_array(image)
    H, W = img_np.shape[:2]
    if mask is None:
        raise InputError("fit_gaussians_to_photo needs the object mask (H, W); segment the photo first")
    m_np = np.clip(as_mask_array(mask, (H, W)), 0.0, 1.0)
    if int((m_np > 0.5).sum()) < MIN_MASK_PIXELS:
        raise InputError(f"fit_gaussians_to_photo: the mask has {int((m_np > 0.5).sum())} pixels; at least "
                         f"{MIN_MASK_PIXELS} are needed. Check the segmentation (empty or tiny mask).")
    object_height = _check_number("object_height", object_height, lambda x: x > 0, "a positive number of metres")
    iou_threshold = _check_number("iou_threshold", iou_threshold, lambda x: 0 <= x <= 1, "in [0, 1]")
    if max_color_error is not None:
        max_color_error = _check_number("max_color_error", max_color_error, lambda x: 0 <= x <= 1,
                                        "in [0, 1] (0 or None = not checked)")
    ground_height = _check_number("ground_height", ground_height, lambda x: True, "a finite height in metres")
    colour_weight = _check_number("colour_weight", colour_weight, lambda x: x >= 0, ">= 0")
    if focal is not None:
        focal = _check_number("focal", focal, lambda x: x > 0, "a positive focal length in pixels (or None)")
    if principal_point is not None:
        try:
            cx, cy = (float(v) for v in principal_point)
        except (TypeError, ValueError) as exc:
            raise InputError("fit_gaussians_to_photo: principal_point must be (cx, cy) in pixels") from exc
        if not (math.isfinite(cx) and math.isfinite(cy)):
            raise InputError(f"fit_gaussians_to_photo: principal_point must be finite; got {principal_point}")
    else:
        cx, cy = W / 2.0, H / 2.0
    if not levels or any(int(s) < 8 or int(n) < 0 for s, n in levels):
        raise InputError("fit_gaussians_to_photo: levels must be (max side >= 8 px, steps >= 0) pairs")

    img = torch.from_numpy(img_np)
    m = torch.from_numpy(m_np.astype(np.float32))

    # 1. Normalise by the robust extents of the significant centres.
    sig = g_in.opacities >= SIGNIFICANT_OPACITY
    pts = g_in.means[sig] if int(sig.sum()) >= 8 else g_in.means
    lo = torch.quantile(pts.double(), 0.02, dim=0)
    hi = torch.quantile(pts.double(), 0.98, dim=0)
    centre = 0.5 * (lo + hi)
    extent = float((hi - lo).max())
    if not (extent > 0 and math.isfinite(extent)):
        raise InputError("fit_gaussians_to_photo: the Gaussians have no extent (all centres coincide)")
    n = len(g_in)
    preps: dict = {}
    coverage: dict = {}  # level size -> (Gaussians rendered, worst coverage of the probe views)

    def get_prep(budget: int) -> _Prep:
        budget = min(int(budget), n)
        if budget not in preps:
            preps[budget] = _prep(g_in, centre, extent, _subset(g_in.means, budget, g_in.opacities, seed + budget))
        return preps[budget]

    levels = [(int(s), int(k)) for s, k in levels]
    box_rows = torch.nonzero(m.amax(dim=1) > 0.5)[:, 0]
    box_cols = torch.nonzero(m.amax(dim=0) > 0.5)[:, 0]
    object_side = math.sqrt(float(box_rows[-1] - box_rows[0] + 1) * float(box_cols[-1] - box_cols[0] + 1))
    rows = torch.nonzero(torch.from_numpy(m_np > 0.5).any(dim=1))[:, 0]
    mask_h = float(rows[-1] - rows[0] + 1)
    side = float(max(H, W))
    f0 = focal if focal is not None else 0.5 * H / math.tan(math.radians(DEFAULT_FOV_Y) / 2)
    f_lo = 0.5 * H / math.tan(math.radians(FOV_RANGE[1]) / 2)
    f_hi = 0.5 * H / math.tan(math.radians(FOV_RANGE[0]) / 2)
    full_budget = min(n, int(max_fit_gaussians))

    def start_params(R0: torch.Tensor, prep: _Prep, uv: Sequence[float]) -> _Params:
        """R0 at depth 1, its projected height (2-98 %) the mask's, its centre at ``uv`` (photo px)."""
        p_rot = prep.means @ R0.T
        ph = float(torch.quantile(p_rot[:, 1], 0.98) - torch.quantile(p_rot[:, 1], 0.02))
        return _Params(R0, math.log(mask_h / max(ph, 1e-3)), uv, math.log(f0), side)

    def prep_for(lv: _Level, last: bool = False, per_pixel: Optional[float] = None) -> _Prep:
        """The Gaussians a level renders: up to max_fit_gaussians at the finest level; at the
        coarser ones a stratified subset (``_subset``) of about ``per_pixel`` per mask pixel,
        doubled until it covers what the finest level's set covers (``_coverage``)."""
        if last:
            return get_prep(full_budget)
        key = (lv.width, lv.height)
        if key in coverage:  # a second round comes back to the same levels
            return get_prep(coverage[key][0])
        if per_pixel is None:
            per_pixel = FINE_PER_PIXEL
        budget = min(full_budget, max(MIN_LEVEL_GAUSSIANS, int(per_pixel * float(lv.mask.sum()))))
        if budget >= full_budget:
            coverage[key] = (budget, 1.0)
            return get_prep(full_budget)
        ref = get_prep(full_budget)
        uv = (cx, cy)
        probes = [start_params(R, ref, uv) for R in _probe_rotations()]
        with torch.no_grad():
            ref_alpha = [_render(ref, q, lv, cx, cy, colors=False).alpha.clamp(0, 1) for q in probes]
        while True:
            cov = _coverage(get_prep(budget), probes, ref_alpha, lv, cx, cy)
            if cov >= MIN_COVERAGE or budget >= full_budget:
                break
            budget = min(full_budget, 2 * budget)
        coverage[key] = (budget, cov)
        return get_prep(budget)

    lv0 = _level(img, m, min(COARSE_SIDE, levels[0][0]), object_side)
    prep_c = prep_for(lv0, per_pixel=1.0)  # ranking candidates needs less than refining them
    m_area = float(lv0.mask.sum())
    ys, xs = torch.meshgrid(torch.arange(lv0.height) + 0.5, torch.arange(lv0.width) + 0.5, indexing="ij")
    m_centroid, m_angle, m_elong = _moments(lv0.mask, xs, ys)

    rotations = canonical_rotations(yaw_steps)
    keep = max(1, min(int(keep), rotations.shape[0]))
    total = (rotations.shape[0] + keep * int(screen_steps) + sum(k for _, k in levels[1:])
             + min(keep, FINALISTS) * max(0, levels[0][1] - int(screen_steps)))
    done = 0

    # 2. Coarse search over the canonical frames.
    def coarse_candidate(R0: torch.Tensor) -> _Params:
        # Start: normalised object's projected height matches the mask's, centred on its centroid;
        # then size, position and (elongated outlines) roll corrected from its own render.
        p = start_params(R0, prep_c, (float(m_centroid[0]) / lv0.kx, float(m_centroid[1]) / lv0.ky))
        _align(prep_c, p, lv0, cx, cy, m_area, m_centroid, m_angle, m_elong)
        return p

    cands = []
    for R0 in rotations:
        p = coarse_candidate(R0)
        with torch.no_grad():
            loss, siou, col = _losses(_render(prep_c, p, lv0, cx, cy), lv0, colour_weight)
        cands.append({"params": p, "loss": float(loss), "soft_iou": float(siou), "colour": float(col),
                      "rotation": p.R0.clone(), "frame": R0})
        done += 1
        report(progress, done, total)
    order = sorted(range(len(cands)), key=lambda i: cands[i]["loss"])
    timings = {"coarse": time.perf_counter() - t_start}

    trace: dict = {}

    def refine(p: _Params, prep: _Prep, lv: _Level, steps: int, lr0: float, *, plateau: bool = False,
               check_at: int = 0, give_up=None) -> bool:
        """``steps`` Adam steps on ``p`` (cosine-decayed rate). ``plateau``: stop early once the
        loss has not improved by PLATEAU_REL (relative) for PLATEAU_STEPS steps, after at least a
        third of the steps, and go back to the best parameters seen. ``give_up(loss)`` is asked
        after ``check_at`` steps (the lower of the last two losses); True stops the run and
        returns False (the candidate is dropped)."""
        nonlocal done
        if steps <= 0:
            return True
        groups = [{"params": [p.omega], "lr": lr0}, {"params": [p.log_sigma], "lr": lr0},
                  {"params": [p.uv], "lr": lr0 * 0.25}]
        if focal is None:
            groups.append({"params": [p.log_f], "lr": lr0})
        opt = _Adam(groups, betas=(0.8, 0.95))
        losses = trace.setdefault((lv.width, id(p)), [])
        best, since, best_state = float("inf"), 0, None
        min_steps = max(PLATEAU_STEPS + 1, steps // 3)
        for step in range(steps):
            decay = 0.5 * (1 + math.cos(math.pi * step / steps)) * 0.9 + 0.1
            for gr, base in zip(opt.param_groups, [lr0, lr0, lr0 * 0.25, lr0]):
                gr["lr"] = base * decay
            loss, _, _ = _losses(_render(prep, p, lv, cx, cy), lv, colour_weight)
            value = float(loss.detach())
            losses.append(round(value, 5))
            if give_up is not None and step == check_at and give_up(min(losses[-2:])):
                return False
            if plateau:
                if value < best:
                    if value < best * (1.0 - PLATEAU_REL):
                        since = 0
                    else:
                        since += 1
                    best = value
                    best_state = p.state()
                else:
                    since += 1
                if step + 1 >= min_steps and since >= PLATEAU_STEPS:
                    p.load_state(best_state)
                    return True
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            with torch.no_grad():
                p.log_f.clamp_(math.log(f_lo), math.log(f_hi))
            done += 1
            report(progress, done, total)
        return True

    # 3. Refinement: the best few compete at the first level (a short run each), the best two of
    # those finish that level, and the better of them goes on coarse to fine. (After the short run
    # a candidate that is still turning towards the right orientation can trail a wrong one that
    # has already settled: a thin bar seen along a wrong axis.)
    lv_first = _level(img, m, levels[0][0], object_side)
    prep_1 = prep_for(lv_first, last=len(levels) == 1)
    lv_last = _level(img, m, levels[-1][0], object_side)
    prep_all = _prep(g_in, centre, extent)

    def score(p: _Params) -> tuple[float, float]:
        with torch.no_grad():
            loss, siou, _ = _losses(_render(prep_1, p, lv_first, cx, cy), lv_first, colour_weight)
        return float(loss), float(siou)

    def run_round(starts: list, tag: str) -> dict:
        """Contenders from ``starts`` (params), the finalists, the winner refined to the finest
        level and scored there with every Gaussian."""
        contenders = []
        halfway: list = []  # each contender's loss after half its short run

        def behind(loss: float) -> bool:
            halfway.append(loss)
            return CONTENDER_MARGIN is not None and loss > min(halfway) + CONTENDER_MARGIN

        for frame, p0 in starts:
            p = p0.clone()
            kept = refine(p, prep_1, lv_first, int(screen_steps), lr, check_at=int(screen_steps) // 2, give_up=behind)
            loss, siou = score(p)
            contenders.append({"params": p, "frame": frame, "start_rotation": p0.rotation().detach(),
                               "rotation": p.rotation().detach(), "loss": loss if kept else float("inf"),
                               "soft_iou": siou, "round": tag, "dropped": not kept})
        timings[f"contenders{tag}"] = time.perf_counter() - t_start
        ranked = sorted((c for c in contenders if not c["dropped"]), key=lambda c: c["loss"])
        finalists = [c for c in ranked[:FINALISTS]
                     if CONTENDER_MARGIN is None or c["loss"] <= ranked[0]["loss"] + CONTENDER_MARGIN]
        for c in finalists:
            refine(c["params"], prep_1, lv_first, max(0, levels[0][1] - int(screen_steps)), lr * 0.7)
            c["final_loss"], c["final_soft_iou"] = score(c["params"])
            c["final_rotation"] = c["params"].rotation().detach()
        p = min(finalists, key=lambda c: c["final_loss"])["params"]
        for k, (max_side, steps) in enumerate(levels[1:]):
            lv = _level(img, m, max_side, object_side)
            refine(p, prep_for(lv, last=k == len(levels) - 2), lv, steps, lr * 0.5 / (k + 1), plateau=PLATEAU_STEPS > 0)
            timings[f"level{k + 1}{tag}"] = time.perf_counter() - t_start
        # Final score with every Gaussian at the finest level.
        with torch.no_grad():
            out = _render(prep_all, p, lv_last, cx, cy)
            iou = _hard_iou(out.alpha, lv_last.hard)
            _, _, col = _losses(out, lv_last, colour_weight)
        color_error = float(col)
        passed = iou >= iou_threshold and (max_color_error is None or max_color_error <= 0
                                           or color_error <= max_color_error)
        return {"params": p, "iou": iou, "color_error": color_error, "ok": passed, "contenders": contenders,
                "finalists": finalists, "loss": (1.0 - iou) + colour_weight * color_error}

    # The contenders: the ``keep`` best by the loss, plus the best by colour alone among the
    # candidates whose outline is plausible (soft IoU within COLOUR_PICK_IOU_MARGIN of the best), when
    # it is not among them. At 32 px a wrong frame can match the outline better than the right one
    # (the coarsened metal_bar lift seen from above is a bar too: soft IoU 0.89 vs 0.82, colour error
    # 0.15 vs 0.08; it ranks first and the right frame third, fifth before _align measured the size
    # again after the roll); its colours tell them apart.
    picks = list(order[:keep])
    best_siou = max(c["soft_iou"] for c in cands)
    plausible = [i for i in order if cands[i]["soft_iou"] >= best_siou - COLOUR_PICK_IOU_MARGIN]
    by_colour = min(plausible, key=lambda i: cands[i]["colour"])
    if by_colour not in picks:
        picks.append(by_colour)
        total += int(screen_steps)
    best = run_round([(cands[i]["frame"], cands[i]["params"]) for i in picks], "")
    rounds = [best]
    # 3b. When the winner fails the checks, a second round: each first-round finalist turned 180°
    # about the up axis (seen from behind; from its coarse frame and from where it ended) and the
    # next ``keep`` coarse candidates, each unless a start already tried is within RETRY_MIN_ANGLE
    # of it. The better of the two rounds is kept (one that passes the checks, else the lower
    # (1 - IoU) + colour_weight · colour error).
    if not best["ok"] and retry:
        tried = [c["start_rotation"] for c in best["contenders"]]
        starts = []

        def add(frame: torch.Tensor, p0: _Params) -> None:
            R0 = p0.rotation().detach()
            if all(rotation_angle_deg(R0 @ T.T) > RETRY_MIN_ANGLE for T in tried):
                tried.append(R0)
                starts.append((frame, p0))

        turn = _rot_y(math.pi)
        for c in best["finalists"]:
            # Turned about the up axis from its coarse frame (before the roll correction, which
            # depends on the outline seen) and from where it ended (refinement can drift off the
            # flip's axis); each placed like a coarse candidate.
            for R_from in (c["frame"], c["final_rotation"]):
                add(turn @ R_from, coarse_candidate(turn @ R_from))
        n_flips = len(starts)
        for i in order[keep:]:
            if i in picks:
                continue
            if len(starts) >= n_flips + keep:
                break
            add(cands[i]["frame"], cands[i]["params"])
        if starts:
            total += len(starts) * int(screen_steps) + sum(k for _, k in levels[1:]) + min(len(starts), FINALISTS) * max(
                0, levels[0][1] - int(screen_steps))
            second = run_round(starts, "_retry")
            rounds.append(second)
            if (second["ok"], -second["loss"]) > (best["ok"], -best["loss"]):
                best = second
    p, iou, color_error = best["params"], best["iou"], best["color_error"]
    if done < total:  # steps saved by dropped contenders and early stops
        done = total
        report(progress, done, total)
    contenders = [{k: v for k, v in c.items() if k != "params"} for r in rounds for c in r["contenders"]]

    # 4. Into the world: metres, +y up, on the ground; the camera tilted by what the object's pose
    #    relative to it leaves once the object stands upright (level if ``upright`` is off).
    with torch.no_grad():
        R = p.rotation().detach().double()
        Rc = upright_turn(R) if upright else torch.eye(3, dtype=torch.float64)
        f = float(torch.exp(p.log_f))
        s_cam = float(torch.exp(p.log_sigma)) / f
        u, v = float(p.uv[0]) * side, float(p.uv[1]) * side
        t_cam = torch.tensor([(u - cx) / f, -(v - cy) / f, -1.0], dtype=torch.float64)
        # x_cam = (s_cam/extent) R x_in + t_cam - (s_cam/extent) R centre
        a = s_cam / extent
        b = t_cam - a * (R @ centre)
        x_cam = (a * (g_in.means.double() @ R.T) + b) @ Rc.T  # camera at the origin, world axes
        sel = x_cam[sig] if int(sig.sum()) >= 1 else x_cam
        k_m = object_height / max(float(sel[:, 1].max() - sel[:, 1].min()), 1e-12)
        x_k = k_m * x_cam
        sel_k = k_m * sel
        lo_k, hi_k = sel_k.min(0).values, sel_k.max(0).values
        y_off = ground_height - (float(lo_k[1]) if on_ground else 0.5 * float(lo_k[1] + hi_k[1]))
        offset = torch.tensor([-0.5 * float(lo_k[0] + hi_k[0]), y_off, -0.5 * float(lo_k[2] + hi_k[2])],
                              dtype=torch.float64)
        means_w = x_k + offset
        scale = a * k_m
        translation = k_m * (Rc @ b) + offset
        Rf = (Rc @ R).float()
        q_R = rotmat_to_quat(Rf[None])[0]
        quats = _quat_mul(q_R[None].expand(n, 4), F.normalize(g_in.quats, dim=-1))
        covars = None if g_in.covars is None else (scale ** 2) * (Rf @ g_in.covars @ Rf.T)
        sh = g_in.sh
        if sh.shape[1] > 1:
            try:
                sh = rotate_sh(sh, Rf)
            except InputError:
                log.warning("fit_gaussians_to_photo: %d SH coefficients per channel is above degree 3; "
                            "view-dependent colour left unrotated", sh.shape[1])
        out_g = Gaussians(means=means_w.float(), quats=quats, scales=g_in.scales * scale,
                          opacities=g_in.opacities.clone(), sh=sh.clone(), covars=covars,
                          object_ids=None if g_in.object_ids is None else g_in.object_ids.clone())
        dist = float(torch.linalg.vector_norm(offset - (means_w.mean(0))))
        c2w = torch.eye(4)
        c2w[:3, :3] = Rc.float()
        c2w[:3, 3] = offset.float()
        camera = Camera(W, H, f, f, cx, cy, c2w, near=max(1e-4, 0.01 * dist), far=max(100.0, 100.0 * dist))
        overlay = fit_overlay(out_g, camera, img, m)

    colour_ok = max_color_error is None or max_color_error <= 0 or color_error <= max_color_error
    ok = iou >= iou_threshold and colour_ok
    if ok:
        message = f"Lined up with the photo: IoU {iou:.3f} >= {iou_threshold:.2f}."
    elif iou >= iou_threshold:
        message = (f"Could not line the Gaussians up with the photo: the outline matches (IoU {iou:.3f}) but the "
                   f"colours do not (mean error {color_error:.3f} > {max_color_error:.2f}), so the object is "
                   "probably turned the wrong way or is another object with a similar outline (see the overlay). "
                   "Check that the Gaussians are of the object in this photo; or raise max_color_error (0 = off) "
                   "to accept this fit.")
    else:
        message = (f"Could not line the Gaussians up with the photo: the best fit covers the mask with IoU "
                   f"{iou:.3f}, below the threshold {iou_threshold:.2f} (see the overlay: mask green, render "
                   "red). Check that the Gaussians are of the object in this photo and that the mask is that "
                   "object; give the photo's focal length if it is unusual (telephoto or fisheye); or lower "
                   "iou_threshold to accept this fit.")
    result = FitResult(
        gaussians=out_g, camera=camera, iou=iou, color_error=color_error, rotation=Rf, view_rotation=R.float(), scale=scale,
        translation=translation.float(), focal=f, ok=ok, iou_threshold=iou_threshold,
        max_color_error=max_color_error, overlay=overlay,
        message=message, seconds=time.perf_counter() - t_start,
        candidates=[{"rotation": cands[i]["rotation"], "loss": cands[i]["loss"], "soft_iou": cands[i]["soft_iou"]}
                    for i in order],
        info={"trace": trace, "contenders": contenders, "timings": timings, "coverage": coverage, "normalise_centre": centre.tolist(), "normalise_extent": extent,
              "fit_gaussians": sorted(int(q.means.shape[0]) for q in preps.values()), "principal_point": (cx, cy), "focal_fitted": focal is None})
    log.info("fit_gaussians_to_photo: %s", result.report().replace("\n", " "))
    if raise_on_failure:
        result.raise_if_failed()
    return result


def _quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of wxyz quaternions (…, 4)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def fit_overlay(gaussians: Gaussians, camera: Camera, image: torch.Tensor, mask: torch.Tensor,
                max_side: int = 512) -> torch.Tensor:
    """(h, 2w, 3): the render over the (dimmed) photo, beside the silhouettes (mask green, render
    red, overlap yellow), at most ``max_side`` px high/wide per panel."""
    from ..render.rasterize import rasterize

    H, W = mask.shape
    k = min(1.0, float(max_side) / float(max(H, W)))
    w, h = max(2, int(round(W * k))), max(2, int(round(H * k)))
    cam = camera.resized(w, h)
    img = torch.as_tensor(image).float()
    m = torch.as_tensor(mask).float()
    if (w, h) != (W, H):
        img = F.interpolate(img.permute(2, 0, 1)[None], size=(h, w), mode="area")[0].permute(1, 2, 0)
        m = F.interpolate(m[None, None], size=(h, w), mode="area")[0, 0]
    with torch.no_grad():
        out = rasterize(gaussians.detach().to("cpu"), cam)
    a = out.alpha.clamp(0, 1)[..., None]
    left = out.rgb.clamp(0, 1) + (1 - a) * 0.5 * img
    right = torch.stack([a[..., 0], m, torch.zeros_like(m)], -1) * 0.85 + 0.15 * img
    return torch.cat([left, right], dim=1).clamp(0, 1)


__all__ = ["FitError", "FitResult", "canonical_rotations", "fit_gaussians_to_photo", "fit_overlay",
           "rotate_sh", "rotation_angle_deg", "axis_angle_to_matrix", "DEFAULT_IOU_THRESHOLD",
           "DEFAULT_MAX_COLOR_ERROR"]
