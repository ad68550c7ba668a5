"""Physics particles from Gaussians: voxelise the Gaussians, fill the enclosed interior, bind.

Lifted Gaussians describe a surface (LGM) or a shell (the silhouette lift); a hollow shell must
behave as a solid, so the volume inside is filled with particles that drive the physics but are
not rendered. Steps, all vectorised numpy/torch with bounded cost:

1. Each Gaussian (opacity >= ``min_opacity``) stands for a solid (``_boxes``):
   * a volume Gaussian (its thinnest σ at least FLAT_RATIO of the middle one): the box |q_i| <= w_i
     along its principal axes (a round Gaussian's, whose rotation says nothing, from the directions
     to its neighbours: ``_lattice_frames``), w_i = 2σ_i but at most half the step to its nearest
     neighbour along that axis (half the third-nearest distance if none lies along it), and at least
     BOX_FLOOR voxels. Boxes tile: Gaussians on a lattice of step h (any σ from about h/4 up, turned
     any way) mark the cube [first - h/2, last + h/2], the n³ cells they stand for (where their
     summed density falls to half), with flat faces and sharp edges. The union of 1.5σ ellipsoids
     used before is scalloped between the centres, so a cube's face layers were speckled (the
     emptiest 0.1-0.7 of a full one) and its volume off by -8..+11 % (issue 22; docs/accuracy.md);
   * a flat (surface) splat: the ellipsoid of 1.5σ with the covariance widened by (s/2)², so a
     thin sheet still marks a voxel-thick layer and a bent surface does not stick out at box corners.
2. Occupancy on a voxel grid of spacing ``s``: a voxel is occupied when its centre lies in a solid.
   Stencils are clamped to MAX_STAMP_RADIUS voxels (9³), raised up to MAX_STAMP_RADIUS_TYPICAL
   when most of the cloud's Gaussians are that large next to the voxel (few Gaussians at a fine
   spacing) as far as the total stays within STAMP_BUDGET: tiny, huge or degenerate covariances
   cannot blow up the cost (the PhysGaussian filler's known failure is an unclamped search radius).
3. A morphological closing (one voxel) seals pinholes between splats.
4. Interior: an empty voxel is inside when occupied voxels lie in all six axis directions.
5. One particle per solid voxel at its centre, with a small seeded jitter (±0.1 voxel along each axis)
   to avoid grid-aligned artefacts. It was ±¼ voxel: the particles' Voronoi shares of the solid then
   differed by up to half a voxel along each axis while every particle weighs the same, so where
   particles lay farther apart the material was thinner and strained more, and a hanging bar's strain
   from F was 2.2 % below the one from its positions (issue 22; 0.993-0.995 at ±0.1 and ~1.000
   without jitter: the gap goes as the jitter squared; tests/test_sim_anchor.py). The particles share
   the solid's volume equally (every particle of an object weighs
   the same): Σ over solid voxels of s³ Π_j f_j (``_volumes``), where along each axis a voxel
   stands for its own half towards a solid neighbour and, towards an empty one, for the solid up
   to where it ends (measured from the solids during step 2, up to one voxel). A face falling
   inside a voxel layer thus no longer adds or drops a layer's worth of mass: a filled cube's
   particle volume is its volume within 0.1 % on random cubes (it was -8..+11 % with s³ each).
   A flat splat's solid ends at its plane along the world axis its normal is closest to (its
   widened ellipsoid only marks the voxels): a centre past the plane measures a negative reach and
   takes back what its inner neighbour's half claimed beyond the surface. A shell of surface
   splats (the silhouette lift, LGM) then weighs what it encloses at any spacing (a sphere within
   1.3 % at 12 voxels across; it weighed 1.40 times that), not the voxel-thick sheet's extra
   (docs/accuracy.md, "Mass of a filled object"). Flat splats that enclose nothing (a sparse open
   cloud) would weigh nothing: the particles always share MIN_VOXEL_SHARE of the voxels at least.
6. Each Gaussian is bound to the particle of the voxel holding its centre (solid whenever the
   Gaussian stamped it; nearly transparent Gaussians bind to the nearest particle instead), and
   interpolates its motion from its NEIGHBOURS nearest particles (``_interpolation``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch

from ..errors import InputError
from ..types.conditions import Ground
from ..types.gaussians import Gaussians, quat_to_rotmat

log = logging.getLogger("physmotion.sim")


@dataclass
class ParticleSet:
    x: np.ndarray  # (P,3) float32 rest positions
    volume: np.ndarray  # (P,) float32 m^3
    binding: np.ndarray  # (N,) int64: the particle of each Gaussian's voxel
    spacing: float  # voxel edge s (m)
    neighbours: np.ndarray  # (N, NEIGHBOURS) int64: particles each Gaussian interpolates from
    weights: np.ndarray  # (N, NEIGHBOURS) float32, rows sum to 1


def _neighbours(pts: np.ndarray, k: int, query: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """For each point (of ``query``, a mask; all by default): the distance to its k-th nearest other
    point (inf when it has fewer than k within reach, and for the points not queried) and the
    indices of its NEAREST_KEPT nearest (-1 where fewer), by a hash grid: cells about the typical
    spacing, candidates in the 27 cells around each point, at most MAX_PER_CELL points per cell (a
    denser cell contributes only its first MAX_PER_CELL points)."""
    n = pts.shape[0]
    out = np.full(n, np.inf)
    nearest = np.full((n, NEAREST_KEPT), -1, np.int64)
    if n <= k:
        return out, nearest
    lo = pts.min(0)
    ext = pts.max(0) - lo
    # Cells of about two points each if the points filled their box (a flat or thin box counted
    # as at least a cell thick, so a plate or a line gets cells of its spacing); a surface puts
    # more in a cell.
    cell = max(float(ext.max()), 1e-12)
    for _ in range(6):
        cell = max(float(np.prod(np.maximum(ext, cell)) * 2.0 / n) ** (1.0 / 3.0), float(ext.max()) * 1e-4, 1e-12)
    key3 = np.floor((pts - lo) / cell).astype(np.int64)
    dims = key3.max(0) + 3
    key = ((key3[:, 0] + 1) * dims[1] + key3[:, 1] + 1) * dims[2] + key3[:, 2] + 1
    order = np.argsort(key, kind="stable")
    skey = key[order]
    cells, first, count = np.unique(skey, return_index=True, return_counts=True)
    table = np.full((cells.shape[0] + 1, MAX_PER_CELL), -1, np.int64)  # the last row: no cell
    rank = np.arange(n) - np.repeat(first, count)
    kept = rank < MAX_PER_CELL
    table[np.repeat(np.arange(cells.shape[0]), count)[kept], rank[kept]] = order[kept]
    ar = np.arange(-1, 2)
    offs = np.stack(np.meshgrid(ar, ar, ar, indexing="ij"), -1).reshape(-1, 3)
    doff = (offs[:, 0] * dims[1] + offs[:, 1]) * dims[2] + offs[:, 2]
    pts_t = torch.from_numpy(pts).float()
    wanted = np.arange(n) if query is None else np.nonzero(query)[0]
    for c0 in range(0, wanted.shape[0], 8192):
        q = wanted[c0:c0 + 8192]
        nk = key[q][:, None] + doff[None, :]  # (q, 27)
        row = np.searchsorted(cells, nk)
        row = np.where((row < cells.shape[0]) & (cells[np.minimum(row, cells.shape[0] - 1)] == nk), row, cells.shape[0])
        cand = table[row].reshape(q.shape[0], -1)  # (q, 27 * MAX_PER_CELL)
        cand = np.where(cand == q[:, None], -1, cand)
        dist = (pts_t[np.maximum(cand, 0)] - pts_t[q][:, None, :]).norm(dim=-1)
        dist = torch.where(torch.from_numpy(cand >= 0), dist, torch.full_like(dist, float("inf")))
        out[q] = torch.kthvalue(dist, k, dim=1).values.double().numpy()
        near_d, near_i = torch.topk(dist, min(NEAREST_KEPT, dist.shape[1]), dim=1, largest=False)
        idx = np.take_along_axis(cand, near_i.numpy(), 1)
        nearest[q, :idx.shape[1]] = np.where(torch.isfinite(near_d).numpy(), idx, -1)
    return out, nearest


NEAREST_KEPT = 6


def _lattice_frames(pts: np.ndarray, nearest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axes from the neighbours (for round Gaussians, whose rotation says nothing): the first along
    the nearest neighbour, the second towards the nearest one at least 60° off it. On a lattice
    these are its axes, however it is turned, so the boxes keep tiling it. Returns (n,3,3) frames
    (columns) and which points got one (two such neighbours)."""
    valid = nearest >= 0
    d = pts[np.maximum(nearest, 0)] - pts[:, None, :]
    length = np.linalg.norm(d, axis=-1)
    valid &= length > 0
    u = d / np.where(valid, length, 1.0)[..., None]
    first = np.argmax(valid, axis=1)
    e1 = np.take_along_axis(u, first[:, None, None], 1)[:, 0]
    cos = np.abs((u * e1[:, None, :]).sum(-1))
    off = valid & (cos < 0.5)
    second = np.argmax(off, axis=1)
    ok = valid.any(1) & off.any(1)
    e2 = np.take_along_axis(u, second[:, None, None], 1)[:, 0]
    e2 = e2 - (e2 * e1).sum(-1, keepdims=True) * e1
    e2 /= np.maximum(np.linalg.norm(e2, axis=-1, keepdims=True), 1e-30)
    return np.stack([e1, e2, np.cross(e1, e2)], axis=-1), ok


MAX_PER_CELL = 8  # candidates per hash cell in _neighbours


@dataclass
class _Boxes:
    """Each kept Gaussian's solid: centre, world -> shape coordinates map, shape, stencil radius."""

    means: torch.Tensor  # (n,3)
    to_box: torch.Tensor  # (n,3,3): q = to_box @ d; inside when |q|_inf <= 1 (a box) or |q|_2 <= 1 (round)
    round: torch.Tensor  # (n,) bool: a flat splat's ellipsoid instead of a box
    radius: torch.Tensor  # (n,) int64
    limit: int  # the largest radius
    normal: torch.Tensor  # (n,3) a flat splat's unit normal (its thinnest axis); unused for the boxes


@dataclass
class _Shapes:
    """The kept Gaussians (opacity >= min_opacity): centres, principal axes, σ along them, and half
    the step to the neighbours along each axis (the cell a Gaussian of a lattice stands for)."""

    means: torch.Tensor  # (n,3)
    unit: torch.Tensor  # (n,3,3) columns: unit principal axes
    sigma: torch.Tensor  # (n,3)
    flat: torch.Tensor  # (n,) bool: a surface splat (thinnest σ under FLAT_RATIO of the middle one)
    cell: torch.Tensor  # (n,3) half the neighbour step along each axis (inf for the flat ones)


def _shapes(g: Gaussians, min_opacity: float) -> _Shapes:
    keep = g.opacities.detach().cpu() >= min_opacity
    means = g.means.detach().float().cpu()[keep]
    if g.covars is not None:
        evals, unit = torch.linalg.eigh(g.covars.detach().double().cpu()[keep])
        sigma, unit = evals.clamp_min(0).sqrt().float(), unit.float()
    else:
        unit = quat_to_rotmat(g.quats.detach().float().cpu()[keep])
        sigma = g.scales.detach().float().cpu()[keep].abs()
    sigma = torch.nan_to_num(sigma, nan=0.0)
    srt = sigma.sort(dim=1).values
    flat = srt[:, 0] < FLAT_RATIO * srt[:, 1]
    pts = means.numpy().astype(np.float64)
    cell, nearest = _neighbours(pts, 3, ~flat.numpy())  # (flat ones do not use them)
    round_ = (srt[:, 2] <= ROUND_RATIO * srt[:, 0]).numpy()
    if round_.any():
        # ``nearest`` indexes all the points: the frames are taken over all of them, the round ones kept.
        frames, ok = _lattice_frames(pts, nearest)
        frames, ok = frames[round_], ok[round_]
        turn = np.nonzero(round_)[0][ok]
        unit = unit.clone()
        unit[torch.from_numpy(turn)] = torch.from_numpy(frames[ok]).float()
    # Along each axis, half the distance to the nearest neighbour lying along it (within ~25°), so a
    # lattice with different steps along its axes is tiled too; half the third-nearest distance
    # where no neighbour lies along that axis.
    valid = nearest >= 0
    d = pts[np.maximum(nearest, 0)] - pts[:, None, :]
    length = np.where(valid, np.linalg.norm(d, axis=-1), np.inf)
    u = d / np.where(np.isfinite(length) & (length > 0), length, 1.0)[..., None]
    along = np.abs(np.einsum("nkj,nji->nki", u, unit.numpy().astype(np.float64))) > 0.9  # (n, k, 3 axes)
    step = np.where(along, length[..., None], np.inf).min(axis=1)  # (n, 3)
    half_cell = np.where(np.isfinite(step), step, cell[:, None]) / 2
    return _Shapes(means, unit, sigma, flat, torch.from_numpy(half_cell).float())


def _boxes(sh: _Shapes, spacing: float) -> _Boxes:
    """Each Gaussian's solid. A volume Gaussian (no axis under FLAT_RATIO of the middle one): the box
    |q_i| <= half_i along its principal axes (a round one's from its neighbours), half_i = 2σ_i but
    at most half the step to the nearest neighbour along that axis (else half the distance to the
    third nearest), so a lattice's boxes tile it whatever σ, and at least BOX_FLOOR voxels.
    A flat (surface) splat: the ellipsoid of 1.5σ with the covariance widened by (s/2)², which
    marks a voxel-thick sheet whatever its thickness and does not stick out at its corners where a
    surface bends (a tilted box would)."""
    flat = sh.flat
    box_half = torch.minimum(2.0 * sh.sigma, sh.cell).clamp_min(BOX_FLOOR * spacing)
    ell_half = 1.5 * torch.sqrt(sh.sigma**2 + 0.25 * spacing**2)
    half = torch.where(flat[:, None], ell_half, box_half)
    to_box = (sh.unit / half[:, None, :]).transpose(1, 2)
    box_span = (sh.unit.abs() * half[:, None, :]).sum(2)  # the half extent along each world axis
    ell_span = ((sh.unit * half[:, None, :]) ** 2).sum(2).sqrt()
    span = torch.where(flat[:, None], ell_span, box_span)
    need = torch.ceil((span.max(1).values / spacing + 0.5).clamp(0, MAX_STAMP_RADIUS_TYPICAL)).long()
    limit = _stamp_limit(need)
    radius = need.clamp(max=limit)
    thinnest = sh.sigma.argmin(dim=1)
    normal = torch.gather(sh.unit, 2, thinnest[:, None, None].expand(-1, 3, 1))[:, :, 0]
    return _Boxes(sh.means, to_box, flat, radius, limit, normal)


FLAT_RATIO = 0.5  # a Gaussian whose thinnest σ is under this times the middle one is a surface splat
ROUND_RATIO = 1.05  # one whose largest σ is within this of its smallest is round: its box takes its
#                     axes from its neighbours (_lattice_frames)
BOX_FLOOR = 0.75  # voxels: the least half width of a box (a small or flat splat still marks its voxel and its
#                   neighbours' gaps, so a sparse shell of small splats stays closed)
MAX_STAMP_RADIUS = 4  # voxels: a Gaussian larger than most of its cloud stamps at most 9³ voxels
MAX_STAMP_RADIUS_TYPICAL = 12  # voxels: the most a stencil grows to cover the cloud's typical Gaussian
STAMP_BUDGET = 40_000_000  # voxel tests over all Gaussians, beyond which the stencils are not grown


def _stamp_limit(need: torch.Tensor) -> int:
    """The stencil radius limit: MAX_STAMP_RADIUS, raised (up to MAX_STAMP_RADIUS_TYPICAL) to the
    radius 90 % of the Gaussians need when they are large next to the voxel (an object of few
    Gaussians at a fine spacing: clamping them would cut their boxes short and leave gaps), as far
    as the total cost stays within STAMP_BUDGET. Outliers (a huge or degenerate splat among small
    ones) stay clamped, so they cannot blow up the cost or the solid."""
    if need.numel() == 0:
        return MAX_STAMP_RADIUS
    limit = max(MAX_STAMP_RADIUS, int(torch.quantile(need.float(), 0.9).ceil()))
    while limit > MAX_STAMP_RADIUS and float(((2 * need.clamp(max=limit) + 1) ** 3).double().sum()) > STAMP_BUDGET:
        limit -= 1
    return limit


REACH_STEPS = 64  # the reach grids hold how far the solid goes from a voxel centre in 1/64 voxel,
REACH_BACK = 1.0  # from this far before it (a centre past a surface splat's plane) up to one voxel past it,
#                   stored as 1 + (reach + REACH_BACK) * REACH_STEPS (0: no solid holds the centre)


def _occupancy(boxes: _Boxes, origin: np.ndarray, dims: np.ndarray,
               spacing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Voxels whose centre lies in a Gaussian's solid (``_boxes``; module docstring, steps 1-2).

    Also returns ``reach`` (6, *dims) uint8: for voxels whose centre lies in a solid, how far along
    -x, +x, -y, +y, -z, +z the solid holding it goes on (the most over such solids), in
    1/REACH_STEPS of a voxel, at most one voxel; 0 where no solid holds the centre (``_volumes``).
    And ``sheet`` (*dims) bool: voxels whose centre a surface splat's solid holds (``_surface_shift``).
    """
    occ = np.zeros(tuple(int(d) for d in dims), dtype=bool)
    reach = torch.zeros((6, int(np.prod(dims))), dtype=torch.uint8)
    sheet = torch.zeros(int(np.prod(dims)), dtype=torch.bool)
    means, to_box, radius, limit = boxes.means, boxes.to_box, boxes.radius, boxes.limit
    if means.shape[0] == 0:
        return occ, reach.reshape(6, *occ.shape).numpy(), sheet.reshape(occ.shape).numpy()
    centre = torch.floor((means - torch.from_numpy(origin).float()) / spacing).long()
    dims_t = torch.from_numpy(np.asarray(dims)).long()
    o = torch.from_numpy(origin).float()
    for r in range(limit + 1):
        sel = torch.nonzero(radius == r)[:, 0]
        if sel.numel() == 0:
            continue
        ar = torch.arange(-r, r + 1)
        offs = torch.stack(torch.meshgrid(ar, ar, ar, indexing="ij"), -1).reshape(-1, 3)
        chunk = max(1, 2_000_000 // offs.shape[0])
        for c0 in range(0, sel.numel(), chunk):
            idx = sel[c0:c0 + chunk]
            vox = centre[idx][:, None, :] + offs[None]  # (n, k, 3)
            d = (vox.float() + 0.5) * spacing + o - means[idx][:, None, :]
            q = torch.einsum("nij,nkj->nki", to_box[idx], d)
            rnd = boxes.round[idx][:, None]
            # (the grid's margin holds every stencil: no bounds check)
            inside = torch.where(rnd, (q * q).sum(-1) <= 1.0, q.abs().amax(-1) <= 1.0)
            hit = inside.clone()
            hit[:, offs.shape[0] // 2] = True  # the centre voxel always counts
            v = vox[hit].numpy()
            occ[v[:, 0], v[:, 1], v[:, 2]] = True
            # How far each held centre can move along ±world axis j and stay in its solid:
            # |q_i + t T_ij| <= 1 for every box axis i, or |q + t T_j|_2 <= 1.
            gi, ki = torch.nonzero(inside, as_tuple=True)
            if gi.numel() == 0:
                continue
            T = to_box[idx][gi]  # (H, 3 box axes, 3 world axes)
            qh = q[gi, ki][:, :, None]  # (H, 3, 1)
            Ta = T.abs().clamp_min(1e-30)
            up = ((1.0 - torch.sign(T) * qh) / Ta).amin(1)  # (H, 3): reach along +j
            down = ((1.0 + torch.sign(T) * qh) / Ta).amin(1)
            rh = boxes.round[idx][gi]
            if bool(rh.any()):  # ellipsoids: t² |T_j|² + 2 t (q . T_j) + |q|² - 1 = 0
                cc = (T * T).sum(1).clamp_min(1e-30)  # (H, 3)
                qc = (qh * T).sum(1)
                root = (qc * qc - cc * ((qh * qh).sum(1) - 1.0)).clamp_min(0.0).sqrt()
                up = torch.where(rh[:, None], (root - qc) / cc, up)
                down = torch.where(rh[:, None], (root + qc) / cc, down)
                # A surface splat's solid ends at its plane, not at its widened ellipsoid (which is
                # widened only to mark a voxel-thick sheet): along ±j, the signed distance to the plane
                # (negative when the centre lies past it), where the plane faces that axis.
                nrm = boxes.normal[idx][gi]  # (H, 3)
                sn = (nrm * d[gi, ki]).sum(-1, keepdim=True)  # the centre's height over the plane
                facing = rh[:, None] & (nrm.abs() >= nrm.abs().amax(1, keepdim=True))
                nj = torch.where(facing, nrm, torch.ones_like(nrm))
                up = torch.where(facing, -sn / nj, up)
                down = torch.where(facing, sn / nj, down)
                silent = rh[:, None] & ~facing  # a plane along an axis says nothing about where it ends
            else:
                silent = torch.zeros_like(up, dtype=torch.bool)
            lin = ((vox[gi, ki, 0] * dims_t[1] + vox[gi, ki, 1]) * dims_t[2] + vox[gi, ki, 2])
            sheet[lin[rh]] = True
            for j in range(3):
                for side, t in ((0, down[:, j]), (1, up[:, j])):
                    val = (torch.round(((t / spacing).clamp(-REACH_BACK, 1.0) + REACH_BACK) * REACH_STEPS)
                           + 1).to(torch.uint8)
                    val = torch.where(silent[:, j], torch.zeros_like(val), val)
                    reach[2 * j + side].scatter_reduce_(0, lin, val, reduce="amax")
    return occ, reach.reshape(6, *occ.shape).numpy(), sheet.reshape(occ.shape).numpy()


def _volumes(solid: np.ndarray, reach: np.ndarray, vox: np.ndarray, spacing: float,
             below: np.ndarray | None = None) -> np.ndarray:
    """The solid volume each solid voxel stands for: s³ Π_j f_j, f_j the length of solid along axis
    j through its centre that the voxel stands for, in voxels (their sum is the solid's volume).

    Towards a solid neighbour a voxel stands for its own half (1/2); towards an empty one, for the
    solid up to where it ends (its ``reach``, up to one voxel): a face falling inside the voxel
    gives less than a full voxel, a face falling short of the empty neighbour's centre adds that
    part of the neighbour. So a box's voxels add up to its true volume, not to its voxel count.
    Voxels no solid holds (closing, interior fill) count whole. ``below`` (per voxel, in voxels):
    how far under its centre the floor lies, the most it may stand for downwards (-y).
    """
    held = reach.any(axis=0)[tuple(vox.T)]
    padded = np.pad(solid, 1)
    F = np.zeros((vox.shape[0], 3))
    for j in range(3):
        fj = F[:, j]
        for side, step in ((0, -1), (1, 1)):
            nb = vox + 1
            nb[:, j] += step
            code = reach[2 * j + side][tuple(vox.T)].astype(np.float64)
            # (no solid holding the centre says where it ends along this axis: its half)
            r = np.where(code > 0, np.minimum((code - 1) / REACH_STEPS - REACH_BACK, 1.0), 0.5)
            if below is not None and (j, side) == (1, 0):
                r = np.minimum(r, below)
            fj += np.where(padded[tuple(nb.T)] | ~held, 0.5, r)
    # A centre past a surface's plane stands for less than nothing along that axis: it takes back what its inner
    # neighbour's half claimed beyond the surface (a face between the two centres). Only the most negative axis
    # does, times what the others stand for, so two such axes do not make a positive volume.
    worst = F.argmin(axis=1)
    low = np.take_along_axis(F, worst[:, None], 1)[:, 0]
    others = np.where(np.arange(3)[None, :] == worst[:, None], 1.0, np.maximum(F, 0.0)).prod(axis=1)
    f = np.where(low < 0.0, low * others, F.prod(axis=1))
    return (f * spacing**3).astype(np.float32)


CONFORM_MAX = 0.5  # voxels: the most an outer particle moves towards or away from the surface


def _axis_reach(solid: np.ndarray, reach: np.ndarray, vox: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi), each (n, 3): how far the solid goes from each voxel's centre along −j / +j (voxels, from
    ``reach``) where that face neighbour is empty and a solid holding the centre says where it ends; NaN
    elsewhere (a solid neighbour, or no solid that knows)."""
    padded = np.pad(solid, 1)
    held = reach.any(axis=0)[tuple(vox.T)]
    out = []
    for side, step in ((0, -1), (1, 1)):
        r = np.full((vox.shape[0], 3), np.nan)
        for j in range(3):
            nb = vox + 1
            nb[:, j] += step
            code = reach[2 * j + side][tuple(vox.T)].astype(np.float64)
            known = ~padded[tuple(nb.T)] & held & (code > 0)
            r[known, j] = np.minimum((code[known] - 1) / REACH_STEPS - REACH_BACK, 1.0)
        out.append(r)
    return out[0], out[1]


def _conform(solid: np.ndarray, reach: np.ndarray, sheet: np.ndarray,
             vox: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(keep, shift, normal, probe): which solid voxels get a particle, and where it goes (voxels from
    the centre, ``_surface_shift``) along which normal, for the voxels a surface splat's solid holds
    (``sheet``); others keep their particle at the centre (normal 0). ``probe``: the blurred normal of
    the other kept voxels on the surface (0 elsewhere), for ``_splat_planes``.

    Dropped: voxels whose centre lies on or past the surface (a surface splat's plane) along an axis
    where the body goes on behind them (the face neighbour opposite is solid). The voxel-thick sheet a
    flat splat marks sticks out of the body by up to a voxel, and a particle there sat outside the
    object (a 0.2 m sphere of splats: up to 0.8 spacings past its surface; a slab's faces 0.6 past).
    Their neighbour behind, now on the surface, learns the plane from them (one voxel further on).
    """
    n = vox.shape[0]
    on = sheet[tuple(vox.T)]
    padded = np.pad(solid, 1)
    lo, hi = _axis_reach(solid, reach, vox)
    drop = np.zeros(n, dtype=bool)
    index = np.full(padded.shape, -1, dtype=np.int64)
    index[tuple((vox + 1).T)] = np.arange(n)
    given = [np.full((n, 3), np.nan), np.full((n, 3), np.nan)]  # (lo, hi) the neighbour behind learns
    for j in range(3):
        for r, step, side in ((lo[:, j], 1, 0), (hi[:, j], -1, 1)):
            nb = vox + 1
            nb[:, j] += step
            past = on & (r <= 0.0) & padded[tuple(nb.T)]
            drop |= past
            behind = index[tuple(nb[past].T)]
            given[side][behind, j] = np.fmax(given[side][behind, j], 1.0 + r[past])
    if drop.all():
        drop[:] = False
    keep = ~drop
    kept = np.zeros_like(solid)
    kept[tuple(vox[keep].T)] = True
    klo, khi = _axis_reach(kept, reach, vox[keep])
    klo = np.where(np.isnan(klo), given[0][keep], klo)
    khi = np.where(np.isnan(khi), given[1][keep], khi)
    learned = ~np.isnan(given[0]).all(axis=1) | ~np.isnan(given[1]).all(axis=1)
    kvox = vox[keep]
    shift, normal = _surface_shift(kept, klo, khi, kvox)
    moved = (on | learned)[keep, None]
    shift, normal = shift * moved, normal * moved
    # The rest of the surface (voxels the closing added, or that no splat's solid says where it ends):
    # the splats near them may still place them (``_splat_planes``); their blurred normal to start from.
    pk = np.pad(kept, 1)
    surface = np.zeros(kvox.shape[0], dtype=bool)
    for j in range(3):
        for step in (-1, 1):
            nb = kvox + 1
            nb[:, j] += step
            surface |= ~pk[tuple(nb.T)]
    probe = surface & (np.abs(normal).sum(axis=1) == 0)
    blurred = np.zeros_like(normal)
    if probe.any():
        blurred[probe] = _normals(kept, kvox[probe])
    return keep, shift, normal, blurred


def _splat_planes(centre: np.ndarray, shift: np.ndarray, normal: np.ndarray, probe: np.ndarray, means: np.ndarray,
                  normals: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Refine the outer particles' (those with a ``normal``, or a ``probe`` one) shift from the surface splats near them: the
    planes of the SPLAT_PLANES nearest within 1.5 spacings (each splat's normal turned to agree with
    the voxel's), averaged with weights 1 / (distance + spacing / 10), give the normal and the signed
    height h of the voxel's centre over the surface; the particle goes to half a spacing under it,
    (−h/s − ½)·n in voxels, at most CONFORM_MAX + ½. Where no splat is that near, the voxel estimate
    (``_surface_shift``) stays. The voxel estimate reads the surface off the solids' ends (1/64 voxel
    steps, one axis) and a blurred normal; the splats are the surface."""
    from scipy.spatial import cKDTree

    guide = np.where((np.abs(normal).sum(axis=1) > 0)[:, None], normal, probe)
    todo = np.nonzero(np.abs(guide).sum(axis=1) > 0)[0]
    if todo.size == 0 or means.shape[0] == 0:
        return shift, normal
    k = min(SPLAT_PLANES, means.shape[0])
    dist, idx = cKDTree(means).query(centre[todo], k=k, distance_upper_bound=1.5 * spacing)
    dist, idx = dist.reshape(todo.size, k), idx.reshape(todo.size, k)
    ok = np.isfinite(dist)
    safe = np.where(ok, idx, 0)
    nk = normals[safe]  # (t, k, 3)
    nk = nk * np.where((nk * guide[todo, None, :]).sum(-1, keepdims=True) < 0, -1.0, 1.0)
    w = np.where(ok, 1.0 / (np.where(ok, dist, 0.0) + 0.1 * spacing), 0.0)[..., None]
    n = (w * nk).sum(1)
    nn = np.sqrt((n * n).sum(-1, keepdims=True))
    h = (w[..., 0] * (nk * (centre[todo, None, :] - means[safe])).sum(-1)).sum(1) / np.maximum(w[..., 0].sum(1), 1e-30)
    good = ok.any(1) & (nn[:, 0] > 0.5 * w[..., 0].sum(1) / np.maximum(w[..., 0].sum(1), 1e-30))
    n = n / np.maximum(nn, 1e-12)
    step = (-h / spacing - 0.5)[:, None] * n
    size = np.sqrt((step * step).sum(-1, keepdims=True))
    step = step * np.minimum(1.0, (CONFORM_MAX + 0.5) / np.maximum(size, 1e-12))
    shift, normal = shift.copy(), normal.copy()
    shift[todo[good]] = step[good]
    normal[todo[good]] = n[good]
    return shift, normal


SPLAT_PLANES = 4  # splats whose planes place an outer particle


def _normals(solid: np.ndarray, vox: np.ndarray) -> np.ndarray:
    """Unit outward normals at the voxels ``vox``: minus the gradient of the solid's indicator blurred by a
    Gaussian of NORMAL_SIGMA voxels (central differences); (0, 0, 0) where it is flat."""
    r = int(math.ceil(3 * NORMAL_SIGMA))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=torch.float32) / NORMAL_SIGMA) ** 2)
    k = k / k.sum()
    lo, hi = np.maximum(vox.min(axis=0) - r - 2, 0), np.minimum(vox.max(axis=0) + r + 3, solid.shape)
    f = torch.from_numpy(solid[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].astype(np.float32))[None, None]
    for ax in range(3):
        shape = [1, 1, 1, 1, 1]
        shape[2 + ax] = k.numel()
        pad = [0, 0, 0, 0, 0, 0]
        pad[2 * (2 - ax)] = pad[2 * (2 - ax) + 1] = r
        f = torch.nn.functional.conv3d(torch.nn.functional.pad(f, pad), k.reshape(shape))
    f = f[0, 0].numpy()
    v = vox - lo
    g = np.zeros((vox.shape[0], 3))
    for ax in range(3):
        up, dn = v.copy(), v.copy()
        up[:, ax] += 1
        dn[:, ax] -= 1
        g[:, ax] = 0.5 * (f[tuple(dn.T)] - f[tuple(up.T)])
    n = np.sqrt((g * g).sum(axis=1, keepdims=True))
    return np.where(n > 1e-6, g / np.maximum(n, 1e-12), 0.0)


NORMAL_SIGMA = 1.0  # voxels: the blur the surface normals are taken from


def _surface_shift(solid: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                   vox: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per solid voxel, where its particle goes (in voxels, from the voxel's centre) so that the outer
    layer lies half a spacing inside the surface, along the surface's normal; (0, 0, 0) inside. Also the
    unit normal it moved along ((0, 0, 0) where it did not).

    A voxel centre on a lattice sits anywhere from 0 to about one voxel inside the surface, so a round
    body's outer particles make a polygon of flats (a disc 16 cells across had a bottom row 75 mm wide:
    rolling over its edge lifted the centre by half a spacing, more energy than a slow roll has, and a
    rigid disc pushed along the ground rocked where it should roll; docs/accuracy.md, "Rolling").
    The normal n comes from the blurred solid (``_normals``); the distance from the centre to the
    surface from the solids' own ends (``lo``, ``hi``: ``_axis_reach``): along the axis j closest to n on whose side
    the face neighbour is empty and the solids say where they end (r_j voxels away), the plane lies
    d = r_j·|n_j| from the centre. The particle moves by (d − ½)·n, at most CONFORM_MAX. Along an
    axis with both neighbours empty (a sheet one voxel thick) it goes to the middle of the solid
    there instead. Voxels with no such axis (inside, or held by no solid that knows) stay.
    """
    both = ~np.isnan(lo) & ~np.isnan(hi)
    out = np.where(both, 0.5 * (np.nan_to_num(hi) - np.nan_to_num(lo)), 0.0)
    n = _normals(solid, vox)
    r = np.where(n > 0, hi, lo)  # the reach on the side the normal points to
    usable = ~np.isnan(r) & ~both & (np.abs(n) > 0.3)
    score = np.where(usable, np.abs(n), -1.0)
    j = score.argmax(axis=1)
    rows = np.arange(vox.shape[0])
    ok = score[rows, j] > 0
    d = np.where(ok, np.nan_to_num(r[rows, j]) * np.abs(n[rows, j]), 0.5)
    out = out + np.where(ok[:, None], (d - 0.5)[:, None] * n, 0.0)
    size = np.sqrt((out * out).sum(axis=1, keepdims=True))
    return out * np.minimum(1.0, CONFORM_MAX / np.maximum(size, 1e-12)), np.where(ok[:, None], n, 0.0)


def _nearest(q: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Index of the nearest point of ``pts`` for each query (chunked brute force; used for few queries)."""
    pts_t = torch.from_numpy(pts).float()
    out = []
    for c0 in range(0, q.shape[0], 256):
        d = torch.cdist(torch.from_numpy(q[c0:c0 + 256]).float(), pts_t)
        out.append(d.argmin(dim=1))
    return torch.cat(out).numpy()


def _close(occ: np.ndarray) -> np.ndarray:
    """Binary closing with a 3x3x3 cross (dilate then erode), in numpy."""

    def shift_or(a):
        out = a.copy()
        for ax in range(3):
            out[(slice(None),) * ax + (slice(1, None),)] |= a[(slice(None),) * ax + (slice(None, -1),)]
            out[(slice(None),) * ax + (slice(None, -1),)] |= a[(slice(None),) * ax + (slice(1, None),)]
        return out

    def shift_and(a):
        out = a.copy()
        for ax in range(3):
            out[(slice(None),) * ax + (slice(1, None),)] &= a[(slice(None),) * ax + (slice(None, -1),)]
            out[(slice(None),) * ax + (slice(None, -1),)] &= a[(slice(None),) * ax + (slice(1, None),)]
        return out

    padded = np.pad(occ, 1)
    return shift_and(shift_or(padded))[1:-1, 1:-1, 1:-1]


def _interior(occ: np.ndarray) -> np.ndarray:
    """Empty voxels with occupied voxels in all six axis directions."""
    inside = ~occ
    for ax in range(3):
        fwd = np.maximum.accumulate(occ, axis=ax)
        bwd = np.flip(np.maximum.accumulate(np.flip(occ, axis=ax), axis=ax), axis=ax)
        inside &= fwd & bwd
    return inside


def fill_particles(
    gaussians: Gaussians,
    spacing: float,
    *,
    max_particles: int = 200_000,
    jitter: float = 0.1,
    seed: int = 0,
    fill_interior: bool = True,
    min_opacity: float = 0.1,
    floor: float | None = None,
    conform: bool = False,
) -> ParticleSet:
    """Sample physics particles filling the solid the Gaussians enclose (see module docstring).

    ``floor`` (a height in metres, e.g. the ground's): no particle is placed below it. The splats
    of an object resting on the ground reach a little below it (a ball's lowest splat is centred on
    the ground), and particles there would start inside the ground.
    ``conform`` (off by default; ``simulate`` turns it on for rigid bodies: docs/accuracy.md, "Rolling"):
    where surface splats bound the solid, no particle sits outside the surface and the outermost ones
    sit half a spacing inside it along its normal (``_conform``), not at their voxels' centres, so a
    round body's underside is round. Volume Gaussians (boxes, which tile a lattice) are left as they are.
    """
    if len(gaussians) == 0:
        raise InputError("Cannot simulate an empty set of Gaussians: the object has no Gaussians")
    if not (math.isfinite(spacing) and spacing > 0):
        raise InputError(f"particle spacing must be positive; got {spacing}")
    means = gaussians.means.detach().float().cpu().numpy()
    lo = means.min(axis=0)
    hi = means.max(axis=0)
    extent = hi - lo
    # Refuse absurd grids before allocating them (each voxel costs ~16 bytes here: occupancy, the
    # six reach grids, the particle index).
    cells = np.ceil(extent / spacing) + 8
    if float(np.prod(cells)) > 4.0e8:
        raise InputError(f"The particle grid would have {float(np.prod(cells)):.3g} voxels "
                         f"(object {extent.round(3).tolist()} m at spacing {spacing:.3g} m). "
                         "Lower grid_res or check the object's scale.")

    shapes = _shapes(gaussians, min_opacity)
    while True:
        boxes = _boxes(shapes, spacing)
        margin = max(boxes.limit, MAX_STAMP_RADIUS)  # voxels: room for the stencils around the centres
        origin = lo - 3.0 * spacing - margin * spacing  # (a stencil reaches at most margin voxels)
        dims = np.ceil((hi - origin) / spacing).astype(np.int64) + 4 + margin
        occ, reach, sheet = _occupancy(boxes, origin, dims, spacing)
        occ = _close(occ)
        solid = occ | _interior(occ) if fill_interior else occ
        if floor is not None:
            rows = origin[1] + (np.arange(solid.shape[1]) + 0.5) * spacing
            solid[:, rows < float(floor), :] = False
            if not solid.any():
                raise InputError(f"The whole object lies below the floor at y={floor:.4g} m; raise it or lower the ground")
        count = int(solid.sum())
        if count <= max_particles:
            break
        # Coarsen rather than run out of memory; the caller logs the adaptation via the returned spacing.
        spacing = spacing * (count / max_particles) ** (1.0 / 3.0) * 1.02

    vox_all = np.argwhere(solid)
    vox = vox_all
    if conform:  # no particle outside the surface; the outer ones half a spacing inside it
        keep, shift, normal, probe = _conform(solid, reach, sheet, vox_all)
        vox = vox_all[keep]
    # Particle index of every solid voxel, for binding.
    index_grid = np.full(tuple(dims), -1, dtype=np.int64)
    index_grid[vox[:, 0], vox[:, 1], vox[:, 2]] = np.arange(vox.shape[0])
    rng = np.random.default_rng(seed)
    jit = rng.uniform(-jitter, jitter, size=vox.shape)
    if conform:
        flat = boxes.round.numpy()
        if flat.any():  # where the splats themselves are near, their planes say where the surface is
            shift, normal = _splat_planes(origin + (vox + 0.5) * spacing, shift, normal, probe,
                                          boxes.means.numpy()[flat].astype(np.float64),
                                          boxes.normal.numpy()[flat].astype(np.float64), spacing)
        # an outer particle's jitter only along the surface: across it, it would be roughness
        jit = jit - (jit * normal).sum(axis=1, keepdims=True) * normal + shift
    x = origin + (vox + 0.5 + jit) * spacing
    if floor is not None:
        x[:, 1] = np.maximum(x[:, 1], float(floor))  # the jitter must not push a particle under it

    centre_idx = np.clip(np.floor((means - origin) / spacing).astype(np.int64), 0, dims - 1)
    binding = index_grid[centre_idx[:, 0], centre_idx[:, 1], centre_idx[:, 2]]
    unbound = np.nonzero(binding < 0)[0]  # nearly transparent Gaussians that stamped nothing
    if unbound.size:
        binding[unbound] = _nearest(means[unbound], x)

    neighbours, weights = _interpolation(means, binding, x, index_grid, origin, spacing, dims)
    # The solid's volume, shared equally: every particle of an object weighs the same.
    below = None if floor is None else (origin[1] + (vox_all[:, 1] + 0.5) * spacing - float(floor)) / spacing
    total = float(_volumes(solid, reach, vox_all, spacing, below).astype(np.float64).sum())
    # Flat splats that enclose nothing (a sparse or open cloud of them) cut their voxels down to nearly nothing:
    # every solid voxel stands for MIN_VOXEL_SHARE of itself at least, so no object weighs nothing.
    total = max(total, MIN_VOXEL_SHARE * vox_all.shape[0] * spacing**3)
    volume = np.full(vox.shape[0], total / vox.shape[0], dtype=np.float32)
    return ParticleSet(
        x=x.astype(np.float32),
        volume=volume,
        binding=binding,
        spacing=float(spacing),
        neighbours=neighbours,
        weights=weights,
    )


MIN_VOXEL_SHARE = 0.1  # the least share of its voxel a particle's volume stands for, on average
NEIGHBOURS = 8  # particles each Gaussian interpolates its motion from


def _interpolation(means, binding, x, index_grid, origin, spacing, dims):
    """The NEIGHBOURS nearest particles of each Gaussian (among the 27 voxels around it) and
    smooth weights (1 - (d / 1.6 s)²)², normalised; the bound particle is always the first.

    A Gaussian then moves with a weighted blend of its neighbours' local affine maps, so the
    splats of one region deform smoothly instead of moving as rigid tiles, one per particle.
    """
    ar = np.arange(-1, 2)
    offs = np.stack(np.meshgrid(ar, ar, ar, indexing="ij"), -1).reshape(-1, 3)
    centre = np.clip(np.floor((means - origin) / spacing).astype(np.int64), 1, dims - 2)
    cand = index_grid[tuple((centre[:, None, :] + offs[None]).transpose(2, 0, 1))]  # (N, 27)
    cand = np.where(cand == binding[:, None], -1, cand)  # the bound particle goes first, below
    d = np.linalg.norm(x[np.maximum(cand, 0)] - means[:, None, :], axis=-1)
    d = np.where(cand >= 0, d, np.inf)
    k = NEIGHBOURS - 1
    order = np.argsort(d, axis=1, kind="stable")[:, :k]
    nb = np.concatenate([binding[:, None], np.take_along_axis(cand, order, 1)], axis=1)
    dist = np.concatenate([np.linalg.norm(x[binding] - means, axis=1)[:, None],
                           np.take_along_axis(d, order, 1)], axis=1)
    w = np.clip(1.0 - (dist / (1.6 * spacing)) ** 2, 0.0, None) ** 2
    w[:, 0] = np.maximum(w[:, 0], 1e-3)  # never zero: a far (transparent) Gaussian follows its particle
    w = np.where(nb >= 0, w, 0.0)
    nb = np.where(nb >= 0, nb, binding[:, None])
    return nb.astype(np.int64), (w / w.sum(1, keepdims=True)).astype(np.float32)


@dataclass
class FilledObjects:
    """Every object's particles, one object after another, and how the Gaussians hang on them."""

    x: np.ndarray  # (P,3) float32 rest positions
    volume: np.ndarray  # (P,) float32 m^3
    particle_object: np.ndarray  # (P,) int64 object id of each particle
    binding: np.ndarray  # (N,) int64: each Gaussian's particle
    neighbours: np.ndarray  # (N, K) int64: particles each Gaussian interpolates from
    weights: np.ndarray  # (N, K) float32, rows sum to 1


def fill_objects(gaussians: Gaussians, obj_ids: np.ndarray, objects: np.ndarray, spacing: float, dx: float,
                 max_particles: int, seed: int, ground: Optional[Ground],
                 conform: Optional[Sequence[bool]] = None) -> FilledObjects:
    """Fill each object on its own (``fill_particles``), so the gap between two objects is never
    filled in; each gets a share of ``max_particles`` in proportion to its Gaussians. ``conform``: per
    object (in the order of ``objects``), whether its outer particles follow its surface."""
    means = gaussians.means.detach().float().cpu().numpy()
    xs, vols, obj_of, binding = [], [], [], np.zeros(len(gaussians), np.int64)
    neighbours = np.zeros((len(gaussians), 1), np.int64)
    weights = np.ones((len(gaussians), 1), np.float32)
    offset = 0
    if ground is not None and float(means[:, 1].min()) < ground.height - 0.5 * dx:
        raise InputError(f"The object reaches below the ground (lowest Gaussian centre y={float(means[:, 1].min()):.4f} m, "
                         f"ground at {ground.height:.4f} m). Raise the object or lower the ground.")
    for k, o in enumerate(objects):
        sel = np.nonzero(obj_ids == o)[0]
        g_o = gaussians.subset(torch.from_numpy(sel))
        g_o.object_ids = None
        share = max(1, int(max_particles * len(sel) / len(gaussians)))
        # Splats resting on the ground reach below it; the particles start at the ground.
        parts = fill_particles(g_o, spacing, max_particles=share, seed=seed + int(o),
                               floor=None if ground is None else ground.height,
                               conform=bool(conform[k]) if conform is not None else False)
        if parts.spacing > spacing * 1.001:
            log.warning("object %d: particle count capped (max_particles=%d): spacing raised from %.4g m to %.4g m",
                        o, max_particles, spacing, parts.spacing)
        xs.append(parts.x)
        vols.append(parts.volume)
        obj_of.append(np.full(len(parts.x), o, np.int64))
        binding[sel] = parts.binding + offset
        if neighbours.shape[1] != parts.neighbours.shape[1]:
            neighbours = np.zeros((len(gaussians), parts.neighbours.shape[1]), np.int64)
            weights = np.zeros((len(gaussians), parts.neighbours.shape[1]), np.float32)
        neighbours[sel] = parts.neighbours + offset
        weights[sel] = parts.weights
        offset += len(parts.x)
    return FilledObjects(np.concatenate(xs), np.concatenate(vols), np.concatenate(obj_of), binding, neighbours,
                         weights)
