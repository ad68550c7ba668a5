"""Filling the background the object leaves behind, without weights.

OpenCV's Telea and Navier-Stokes fills diffuse the colours around the hole inwards: across a hole wider
than a few pixels that is a flat smear, with streaks where Telea's marching fronts meet. A moving object
uncovers exactly that region, so it is what the viewer looks at. Measured on object-shaped holes cut into
real photos with known truth (benchmarks/bench_fill.py, docs/quality.md), two fills were built here:

* ``harmonic_fill`` (the default): the membrane interpolant, each filled pixel the mean of its four
  neighbours with the known pixels around the hole fixed, solved exactly (a sparse direct solve; large holes
  coarse first, then a band along the edge at full size). No streaks, no overshoot; closest to the truth of
  the four on average, in PSNR and SSIM.
* ``patch_fill``: exemplar completion (after Wexler, Shechtman and Irani, "Space-Time Completion of Video",
  2007, with Barnes et al.'s PatchMatch for the nearest-neighbour search; our own implementation). Coarse to
  fine over a pyramid, from the level where the hole is a few pixels deep (started from the harmonic fill
  there) to the full size; at each level a few rounds of: for every patch that touches the hole, find the most
  similar patch lying wholly in the known region (PatchMatch: propagation from the neighbours' matches by jump
  steps, so the whole field updates at once, and a random search at shrinking radii; the coarser level's
  field, upsampled, as the start), then set every hole pixel to the mean of what the patches covering it copy
  there, weighted by how well each matched and how far it reaches into the hole. It invents texture, but
  copies whole structures to wrong places and scores lower: an option, not the default.

Only hole pixels ever change; the known pixels are bit-identical to the input.
"""

from __future__ import annotations

import math
from typing import Optional

import cv2
import numpy as np

from .errors import InputError

FILL_METHODS = ("harmonic", "patch", "telea", "ns")

PATCH_RADIUS = 3  # 7x7 patches
COARSE_DEPTH = 3.0  # the pyramid's top is where the hole is about this many pixels deep
MIN_COARSE_SIDE = 24
COARSE_START = "harmonic"  # how the coarsest level is started before its patches are matched
CONFIDENCE_DECAY = 1.3  # a patch's vote weight falls by this factor per pixel of depth into the hole (Wexler)


def _diffusion(img: np.ndarray, hole: np.ndarray, flags: int, radius: float = 3.0) -> np.ndarray:
    out = np.empty_like(img)
    h8 = hole.astype(np.uint8)
    for c in range(img.shape[2]):
        ch = (np.clip(img[:, :, c], 0.0, 1.0) * 65535.0 + 0.5).astype(np.uint16)
        out[:, :, c] = cv2.inpaint(ch, h8, float(radius), flags).astype(np.float32) / 65535.0
    return out


def _depth(hole: np.ndarray) -> float:
    if not hole.any():
        return 0.0
    return float(cv2.distanceTransform(hole.astype(np.uint8), cv2.DIST_L2, 3).max())


class _Level:
    """One pyramid level: the padded image, which centres are sources (patch wholly known) and targets."""

    def __init__(self, img: np.ndarray, hole: np.ndarray, r: int):
        self.r = r
        self.h, self.w = hole.shape
        self.img = cv2.copyMakeBorder(img, r, r, r, r, cv2.BORDER_REFLECT)
        hp = cv2.copyMakeBorder(hole.astype(np.uint8), r, r, r, r, cv2.BORDER_REFLECT) > 0
        self.hole = hp
        k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
        known_c = cv2.erode((~hp).astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
        known_c[:r], known_c[-r:], known_c[:, :r], known_c[:, -r:] = False, False, False, False
        self.source = known_c
        touch = cv2.dilate(hp.astype(np.uint8), k) > 0
        touch[:r], touch[-r:], touch[:, :r], touch[:, -r:] = False, False, False, False
        self.ty, self.tx = np.nonzero(touch)  # target centres (padded coordinates)
        self.depth = cv2.distanceTransform(hp.astype(np.uint8), cv2.DIST_L2, 3)  # 0 outside the hole
        self.sy_all, self.sx_all = np.nonzero(known_c)
        offs = np.arange(-r, r + 1, 2)  # a stride-2 subset of the patch for matching: 4x4 of 7x7
        self.moy, self.mox = [a.ravel() for a in np.meshgrid(offs, offs, indexing="ij")]

    def distance(self, sy: np.ndarray, sx: np.ndarray) -> np.ndarray:
        img = self.img
        d = np.zeros(self.ty.shape[0], np.float32)
        for oy, ox in zip(self.moy, self.mox):
            diff = img[self.ty + oy, self.tx + ox] - img[sy + oy, sx + ox]
            d += (diff * diff).sum(-1)
        return d


def _patchmatch(L: _Level, sy: np.ndarray, sx: np.ndarray, iters: int, rng: np.random.Generator):
    """Improve the field (sy, sx) of every target centre; returns it and its distances."""
    d = L.distance(sy, sx)
    src = L.source
    Hp, Wp = src.shape
    index = -np.ones((Hp, Wp), np.int64)
    index[L.ty, L.tx] = np.arange(L.ty.shape[0])
    max_r = max(Hp, Wp)

    def consider(cy, cx):
        nonlocal sy, sx, d
        cy = np.clip(cy, 0, Hp - 1)
        cx = np.clip(cx, 0, Wp - 1)
        ok = src[cy, cx]
        if not ok.any():
            return
        dc = np.full_like(d, np.inf)
        sel = np.nonzero(ok)[0]
        # distance only where the candidate is a valid source
        sub = _Sub(L, sel)
        dc[sel] = sub.distance(cy[sel], cx[sel])
        better = dc < d
        sy, sx, d = np.where(better, cy, sy), np.where(better, cx, sx), np.where(better, dc, d)

    for it in range(iters):
        for step in (8, 4, 2, 1):
            for dy, dx in ((0, step), (step, 0), (0, -step), (-step, 0)):
                ny, nx = L.ty + dy, L.tx + dx
                inb = (ny >= 0) & (ny < Hp) & (nx >= 0) & (nx < Wp)
                j = index[np.clip(ny, 0, Hp - 1), np.clip(nx, 0, Wp - 1)]
                has = inb & (j >= 0)
                cy = np.where(has, sy[np.maximum(j, 0)] - dy, sy)
                cx = np.where(has, sx[np.maximum(j, 0)] - dx, sx)
                consider(cy, cx)
        rad = max_r
        while rad >= 1:
            cy = sy + rng.integers(-rad, rad + 1, sy.shape[0])
            cx = sx + rng.integers(-rad, rad + 1, sx.shape[0])
            consider(cy, cx)
            rad //= 2
    return sy, sx, d


class _Sub:
    """A view of a level restricted to some of its target centres (for candidate distances)."""

    def __init__(self, L: _Level, sel: np.ndarray):
        self.L, self.ty, self.tx = L, L.ty[sel], L.tx[sel]

    def distance(self, sy, sx):
        img, L = self.L.img, self.L
        d = np.zeros(self.ty.shape[0], np.float32)
        for oy, ox in zip(L.moy, L.mox):
            diff = img[self.ty + oy, self.tx + ox] - img[sy + oy, sx + ox]
            d += (diff * diff).sum(-1)
        return d


def _vote(L: _Level, sy: np.ndarray, sx: np.ndarray, d: np.ndarray) -> None:
    """Every hole pixel set to the weighted mean of what the patches covering it copy there (in place)."""
    r = L.r
    Hp, Wp = L.hole.shape
    sigma2 = max(float(np.percentile(d, 75)), 1e-6)
    w = np.exp(-d / (2.0 * sigma2)).astype(np.float64) + 1e-6
    # Patches deeper in the hole copy less reliably (their own pixels are guesses): weighted down by depth.
    w *= CONFIDENCE_DECAY ** (-L.depth[L.ty, L.tx])
    acc = np.zeros((Hp * Wp, 3))
    wsum = np.zeros(Hp * Wp)
    img = L.img
    for oy in range(-r, r + 1):
        for ox in range(-r, r + 1):
            p = (L.ty + oy) * Wp + (L.tx + ox)
            val = img[sy + oy, sx + ox]
            wsum += np.bincount(p, weights=w, minlength=Hp * Wp)
            for c in range(3):
                acc[:, c] += np.bincount(p, weights=w * val[:, c], minlength=Hp * Wp)
    hole = L.hole.ravel()
    has = hole & (wsum > 0)
    flat = img.reshape(-1, 3)
    flat[has] = (acc[has] / wsum[has, None]).astype(np.float32)
    L.img = flat.reshape(Hp, Wp, 3)


def _pyramid(img: np.ndarray, hole: np.ndarray) -> list:
    levels = [(img, hole)]
    while True:
        im, ho = levels[-1]
        h, w = ho.shape
        if _depth(ho) <= COARSE_DEPTH or min(h, w) // 2 < MIN_COARSE_SIDE:
            break
        small = cv2.resize(im, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
        hs = cv2.resize(ho.astype(np.float32), (w // 2, h // 2), interpolation=cv2.INTER_AREA) > 0
        levels.append((small, hs))
    return levels[::-1]


def patch_fill(img: np.ndarray, hole: np.ndarray, *, seed: int = 0, em_iters: int = 4,
               pm_iters: int = 2, r: int = PATCH_RADIUS) -> np.ndarray:
    """Exemplar completion of ``hole`` (H,W bool) in ``img`` (H,W,3 float32 0..1): see the module notes."""
    rng = np.random.default_rng(seed)
    levels = _pyramid(img, hole)
    prev_img = prev_field = None
    for li, (im, ho) in enumerate(levels):
        h, w = ho.shape
        if prev_img is None:
            start = smooth_fill(im, ho, 1) if COARSE_START == "harmonic" else _diffusion(im, ho, cv2.INPAINT_TELEA)
        else:
            up = cv2.resize(prev_img, (w, h), interpolation=cv2.INTER_LINEAR)
            start = np.where(ho[..., None], up, im).astype(np.float32)
        L = _Level(start, ho, r)
        if L.ty.shape[0] == 0 or L.sy_all.shape[0] == 0:
            prev_img = np.where(ho[..., None], start, im)
            continue
        if prev_field is None:
            k = rng.integers(0, L.sy_all.shape[0], L.ty.shape[0])
            sy, sx = L.sy_all[k], L.sx_all[k]
        else:
            psy, psx, ph, pw = prev_field
            # a target's match at the coarser level, doubled, plus its offset within the 2x2 cell
            cyo, cxo = (L.ty - r) // 2 + r, (L.tx - r) // 2 + r
            cyo, cxo = np.clip(cyo, 0, ph - 1), np.clip(cxo, 0, pw - 1)
            by = (psy[cyo, cxo] - r) * 2 + r + (L.ty - r) % 2
            bx = (psx[cyo, cxo] - r) * 2 + r + (L.tx - r) % 2
            Hp, Wp = L.source.shape
            by, bx = np.clip(by, 0, Hp - 1), np.clip(bx, 0, Wp - 1)
            ok = L.source[by, bx]
            k = rng.integers(0, L.sy_all.shape[0], L.ty.shape[0])
            sy = np.where(ok, by, L.sy_all[k])
            sx = np.where(ok, bx, L.sx_all[k])
        fine = li == len(levels) - 1
        iters = max(1, em_iters // 2) if fine and len(levels) > 1 else em_iters
        for _ in range(iters):
            sy, sx, d = _patchmatch(L, sy, sx, pm_iters, rng)
            _vote(L, sy, sx, d)
        Hp, Wp = L.source.shape
        fy = np.zeros((Hp, Wp), np.int64)
        fx = np.zeros((Hp, Wp), np.int64)
        fy[L.ty, L.tx], fx[L.ty, L.tx] = sy, sx
        prev_field = (fy, fx, Hp, Wp)
        out = L.img[r:r + h, r:r + w]
        prev_img = np.where(ho[..., None], out, im).astype(np.float32)
    return prev_img


def _neighbour_system(hole: np.ndarray, order: int):
    """The sparse (bi)harmonic system over the hole's pixels: L u = 0 (order 1) or L² u = 0 (order 2) with the
    known pixels as boundary values, L the 5-point Laplacian (reflecting at the image's border)."""
    import scipy.sparse as sp

    H, W = hole.shape
    n = H * W
    idx = np.arange(n).reshape(H, W)
    rows, cols, vals = [], [], []
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        ny = np.clip(np.arange(H)[:, None] + dy, 0, H - 1) * np.ones((1, W), int)
        nx = np.clip(np.arange(W)[None, :] + dx, 0, W - 1) * np.ones((H, 1), int)
        j = idx[ny, nx]
        rows.append(idx.ravel())
        cols.append(j.ravel())
        vals.append(np.ones(n))
    rows, cols, vals = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    A = sp.csr_matrix((vals, (rows, cols)), shape=(n, n)) - 4.0 * sp.identity(n, format="csr")
    if order == 2:
        A = A @ A
    return A.tocsr()


def smooth_fill(img: np.ndarray, hole: np.ndarray, order: int = 2) -> np.ndarray:
    """Harmonic (order 1) or biharmonic (order 2) interpolation of the hole from the pixels around it, solved
    exactly over the hole's bounding box (plus a margin) by a sparse direct solve."""
    import scipy.sparse.linalg as spla

    ys, xs = np.nonzero(hole)
    m = 2 * order + 2
    H, W = hole.shape
    y0, y1, x0, x1 = max(0, ys.min() - m), min(H, ys.max() + 1 + m), max(0, xs.min() - m), min(W, xs.max() + 1 + m)
    ho = hole[y0:y1, x0:x1]
    im = img[y0:y1, x0:x1].astype(np.float64)
    A = _neighbour_system(ho, order)
    u = ho.ravel()
    k = ~u
    Auu = A[u][:, u].tocsc()
    Auk = A[u][:, k]
    out = img.copy()
    flat = im.reshape(-1, 3)
    lu = spla.splu(Auu)
    sol = np.stack([lu.solve(-(Auk @ flat[k, c])) for c in range(3)], -1)
    res = flat.copy()
    res[u] = np.clip(sol, 0.0, 1.0)  # the biharmonic interpolant can overshoot
    out[y0:y1, x0:x1] = res.reshape(im.shape).astype(np.float32)
    return out


#: Unknowns above which the harmonic fill is solved at a coarser scale first (then only a band along the hole's
#: edge at full size): a direct solve's memory grows faster than the pixel count.
MAX_DIRECT_UNKNOWNS = 60_000
BAND_PX = 8


def harmonic_fill(img: np.ndarray, hole: np.ndarray) -> np.ndarray:
    """The membrane (Laplace) interpolant of the hole: each filled pixel the mean of its four neighbours, the
    known pixels around it fixed. Smooth, with no fronts meeting in streaks (Telea) and no overshoot
    (biharmonic); on object-shaped holes in real photos it is closer to the truth than either OpenCV fill
    (docs/quality.md). Large holes: solved at a scale with at most ``MAX_DIRECT_UNKNOWNS`` unknowns, upsampled,
    then solved again at full size over a ``BAND_PX`` band along the hole's edge."""
    n = int(hole.sum())
    if n <= MAX_DIRECT_UNKNOWNS:
        return smooth_fill(img, hole, 1)
    H, W = hole.shape
    f = math.sqrt(MAX_DIRECT_UNKNOWNS / n)
    w, h = max(4, int(W * f)), max(4, int(H * f))
    small = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    hs = cv2.dilate((cv2.resize(hole.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) > 0).astype(np.uint8),
                    np.ones((3, 3), np.uint8)) > 0
    if hs.all():
        raise InputError("Cannot fill the background: the hole covers nearly the whole image")
    coarse = smooth_fill(small, hs, 1)
    up = cv2.resize(coarse, (W, H), interpolation=cv2.INTER_LINEAR)
    pre = np.where(hole[..., None], up, img).astype(np.float32)
    dist = cv2.distanceTransform(hole.astype(np.uint8), cv2.DIST_L2, 3)
    band = hole & (dist <= BAND_PX)
    return smooth_fill(pre, band, 1)


def fill_hole(img: np.ndarray, hole: np.ndarray, method: str = "harmonic", *, seed: int = 0) -> np.ndarray:
    """``img`` (H,W,3 float32 0..1) with the pixels of ``hole`` (H,W bool) filled by ``method`` (``FILL_METHODS``:
    "harmonic" the default, "patch" the exemplar completion, "telea"/"ns" OpenCV's fills); every other pixel
    is returned unchanged."""
    if method not in FILL_METHODS:
        raise InputError(f"fill method must be one of {FILL_METHODS}; got {method!r}")
    img = np.ascontiguousarray(img, dtype=np.float32)
    hole = np.asarray(hole, bool)
    if not hole.any():
        return img.copy()
    if hole.all():
        raise InputError("Cannot fill the background: the hole covers the whole image")
    if method == "harmonic":
        out = harmonic_fill(img, hole)
    elif method == "patch":
        out = patch_fill(img, hole, seed=seed)
    else:
        out = _diffusion(img, hole, cv2.INPAINT_TELEA if method == "telea" else cv2.INPAINT_NS, 5.0)
    return np.where(hole[..., None], np.clip(out, 0.0, 1.0), img).astype(np.float32)


def inpaint_background(image, mask, *, dilate_px: Optional[int] = None, method: str = "harmonic",
                       max_side: int = 1024):
    """The photo with the object's region (``mask`` above 1/255: a soft matte's whole extent; grown by
    ``dilate_px``, default ``segment.classic.default_dilate_px``) filled by ``fill_hole``, as an (H,W,3) float32
    tensor; the contract of ``segment.classic.inpaint_background`` (photos larger than ``max_side`` are filled
    at that size and only the hole is upsampled; pixels outside the hole are bit-identical to the input)."""
    import torch

    from .segment.classic import (_ellipse, _grow_for_resampling, _resample_region, _resize_to_max_side,
                                  as_image_array, as_mask_array, default_dilate_px)

    img = as_image_array(image)
    H, W = img.shape[:2]
    # A soft matte's faint edge still holds object colour: the hole covers its whole extent (as segment() does).
    m = as_mask_array(mask, (H, W)) > 1.0 / 255.0
    if not m.any():
        raise InputError("Cannot inpaint the background: the mask is empty (no object pixels)")
    dilate_px = default_dilate_px(H, W) if dilate_px is None else int(dilate_px)
    if dilate_px < 0:
        raise InputError(f"dilate_px must be >= 0; got {dilate_px}")
    hole = m.astype(np.uint8)
    if dilate_px > 0:
        hole = cv2.dilate(hole, _ellipse(dilate_px))
    hole = hole > 0
    if hole.all():
        raise InputError(f"Cannot inpaint the background: the object mask (dilated by {dilate_px} px) covers the "
                         "whole image, so there is nothing to fill from. Use a tighter mask, or a smaller dilate_px.")
    small, scale = _resize_to_max_side(img, max_side)
    if scale >= 1.0:
        filled = fill_hole(img, hole, method)
    else:
        h, w = small.shape[:2]
        hole_s = _grow_for_resampling(cv2.resize(hole.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) > 0)
        if hole_s.all():
            raise InputError("Cannot inpaint the background: the object covers nearly the whole image")
        filled = _resample_region(fill_hole(small, hole_s, method), (H, W), hole, img, cv2.INTER_LINEAR)
    out = np.where(hole[:, :, None], filled, img)
    return torch.from_numpy(np.ascontiguousarray(out.astype(np.float32)))
