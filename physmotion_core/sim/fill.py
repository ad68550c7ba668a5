"""Physics particles from Gaussians: voxelise the Gaussians, fill the enclosed interior, bind.

Lifted Gaussians describe a surface (LGM) or a shell (the silhouette lift); a hollow shell must
behave as a solid, so the volume inside is filled with particles that drive the physics but are
not rendered. Steps, all vectorised numpy with bounded cost:

1. Occupancy on a voxel grid of spacing ``s``: a voxel is occupied when its centre lies within 1.5σ
   of a Gaussian (opacity >= ``min_opacity``) whose covariance is widened by (s/2)², so thin
   surface splats still mark a voxel-thick sheet. Each Gaussian's stencil is clamped to at most
   9³ voxels, so tiny, huge or degenerate covariances cannot blow up the cost (the PhysGaussian
   filler's known failure is an unclamped search radius).
2. A morphological closing (one voxel) seals pinholes between splats.
3. Interior: an empty voxel is inside when occupied voxels lie in all six axis directions.
4. One particle per solid voxel at its centre (with a small seeded jitter to avoid grid-aligned
   artefacts); volume s³.
5. Each Gaussian is bound to the particle of the voxel holding its centre (solid whenever the
   Gaussian stamped it; nearly transparent Gaussians bind to the nearest particle instead), and
   interpolates its motion from its NEIGHBOURS nearest particles (``_interpolation``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Optional

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


def _gaussian_axes(g: Gaussians) -> torch.Tensor:
    """(N,3,3) matrices whose columns are each Gaussian's σ-scaled principal axes."""
    if g.covars is not None:
        evals, evecs = torch.linalg.eigh(g.covars.detach().double().cpu())
        return (evecs * evals.clamp_min(0).sqrt()[:, None, :]).float()
    R = quat_to_rotmat(g.quats.detach().float().cpu())
    return R * g.scales.detach().float().cpu()[:, None, :]


MAX_STAMP_RADIUS = 4  # voxels: the per-Gaussian stencil is at most 9³ voxels, whatever its covariance


def _occupancy(g: Gaussians, origin: np.ndarray, dims: np.ndarray, spacing: float,
               min_opacity: float) -> np.ndarray:
    """Voxels within 1.5σ of a Gaussian whose covariance is widened by the voxel size.

    Widening by (s/2)² makes thin surface splats mark a voxel-thick sheet instead of missing the
    voxel centres; the stencil radius is clamped (MAX_STAMP_RADIUS), so the cost per Gaussian is
    bounded whatever its covariance (tiny, huge or degenerate).
    """
    occ = np.zeros(tuple(int(d) for d in dims), dtype=bool)
    keep = (g.opacities.detach().cpu() >= min_opacity)
    means = g.means.detach().float().cpu()[keep]
    axes = _gaussian_axes(g)[keep]
    if means.shape[0] == 0:
        return occ
    cov = axes @ axes.transpose(1, 2) + (0.25 * spacing**2) * torch.eye(3)
    prec = torch.linalg.inv(cov.double()).float()
    sigma_max = torch.sqrt(torch.linalg.eigvalsh(cov.double()).max(dim=1).values).float()
    radius = torch.clamp(torch.ceil(2.0 * sigma_max / spacing), 0, MAX_STAMP_RADIUS).long()
    centre = torch.floor((means - torch.from_numpy(origin).float()) / spacing).long()
    dims_t = torch.from_numpy(np.asarray(dims)).long()
    o = torch.from_numpy(origin).float()
    for r in range(MAX_STAMP_RADIUS + 1):
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
            m2 = torch.einsum("nki,nij,nkj->nk", d, prec[idx], d)
            hit = (m2 <= 2.25) & (vox >= 0).all(-1) & (vox < dims_t).all(-1)
            hit[:, offs.shape[0] // 2] = True  # the centre voxel always counts
            v = vox[hit & (vox >= 0).all(-1) & (vox < dims_t).all(-1)].numpy()
            occ[v[:, 0], v[:, 1], v[:, 2]] = True
    return occ


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
    jitter: float = 0.25,
    seed: int = 0,
    fill_interior: bool = True,
    min_opacity: float = 0.1,
    floor: float | None = None,
) -> ParticleSet:
    """Sample physics particles filling the solid the Gaussians enclose (see module docstring).

    ``floor`` (a height in metres, e.g. the ground's): no particle is placed below it. The splats
    of an object resting on the ground reach a little below it (a ball's lowest splat is centred on
    the ground), and particles there would start inside the ground.
    """
    if len(gaussians) == 0:
        raise InputError("Cannot simulate an empty set of Gaussians: the object has no Gaussians")
    if not (math.isfinite(spacing) and spacing > 0):
        raise InputError(f"particle spacing must be positive; got {spacing}")
    means = gaussians.means.detach().float().cpu().numpy()
    lo = means.min(axis=0)
    hi = means.max(axis=0)
    extent = hi - lo
    # Refuse absurd grids before allocating them (each voxel costs ~3 bytes here).
    cells = np.ceil(extent / spacing) + 8
    if float(np.prod(cells)) > 4.0e8:
        raise InputError(f"The particle grid would have {float(np.prod(cells)):.3g} voxels "
                         f"(object {extent.round(3).tolist()} m at spacing {spacing:.3g} m). "
                         "Lower grid_res or check the object's scale.")

    origin = lo - 3.0 * spacing - MAX_STAMP_RADIUS * spacing
    dims = np.ceil((hi - origin) / spacing).astype(np.int64) + 4 + MAX_STAMP_RADIUS
    occ = _occupancy(gaussians, origin, dims, spacing, min_opacity)
    occ = _close(occ)
    solid = occ | _interior(occ) if fill_interior else occ
    if floor is not None:
        rows = origin[1] + (np.arange(solid.shape[1]) + 0.5) * spacing
        solid[:, rows < float(floor), :] = False
        if not solid.any():
            raise InputError(f"The whole object lies below the floor at y={floor:.4g} m; raise it or lower the ground")

    count = int(solid.sum())
    if count > max_particles:
        # Coarsen rather than run out of memory; the caller logs the adaptation via the returned spacing.
        factor = (count / max_particles) ** (1.0 / 3.0) * 1.02
        return fill_particles(gaussians, spacing * factor, max_particles=max_particles, jitter=jitter,
                              seed=seed, fill_interior=fill_interior, min_opacity=min_opacity, floor=floor)

    vox = np.argwhere(solid)
    # Particle index of every solid voxel, for binding.
    index_grid = np.full(tuple(dims), -1, dtype=np.int64)
    index_grid[vox[:, 0], vox[:, 1], vox[:, 2]] = np.arange(vox.shape[0])
    rng = np.random.default_rng(seed)
    x = origin + (vox + 0.5 + rng.uniform(-jitter, jitter, size=vox.shape)) * spacing
    if floor is not None:
        x[:, 1] = np.maximum(x[:, 1], float(floor))  # the jitter must not push a particle under it

    centre_idx = np.clip(np.floor((means - origin) / spacing).astype(np.int64), 0, dims - 1)
    binding = index_grid[centre_idx[:, 0], centre_idx[:, 1], centre_idx[:, 2]]
    unbound = np.nonzero(binding < 0)[0]  # nearly transparent Gaussians that stamped nothing
    if unbound.size:
        binding[unbound] = _nearest(means[unbound], x)

    neighbours, weights = _interpolation(means, binding, x, index_grid, origin, spacing, dims)
    return ParticleSet(
        x=x.astype(np.float32),
        volume=np.full(vox.shape[0], spacing**3, dtype=np.float32),
        binding=binding,
        spacing=float(spacing),
        neighbours=neighbours,
        weights=weights,
    )


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
                 max_particles: int, seed: int, ground: Optional[Ground]) -> FilledObjects:
    """Fill each object on its own (``fill_particles``), so the gap between two objects is never
    filled in; each gets a share of ``max_particles`` in proportion to its Gaussians."""
    means = gaussians.means.detach().float().cpu().numpy()
    xs, vols, obj_of, binding = [], [], [], np.zeros(len(gaussians), np.int64)
    neighbours = np.zeros((len(gaussians), 1), np.int64)
    weights = np.ones((len(gaussians), 1), np.float32)
    offset = 0
    if ground is not None and float(means[:, 1].min()) < ground.height - 0.5 * dx:
        raise InputError(f"The object reaches below the ground (lowest Gaussian centre y={float(means[:, 1].min()):.4f} m, "
                         f"ground at {ground.height:.4f} m). Raise the object or lower the ground.")
    for o in objects:
        sel = np.nonzero(obj_ids == o)[0]
        g_o = gaussians.subset(torch.from_numpy(sel))
        g_o.object_ids = None
        share = max(1, int(max_particles * len(sel) / len(gaussians)))
        # Splats resting on the ground reach below it; the particles start at the ground.
        parts = fill_particles(g_o, spacing, max_particles=share, seed=seed + int(o),
                               floor=None if ground is None else ground.height)
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
