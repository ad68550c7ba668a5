"""simulate(): Gaussians + material + conditions → a trajectory (SimResult)."""

from __future__ import annotations

import logging
import math
import time
from typing import Optional

import numpy as np
import torch

from ..errors import InputError
from ..memory import device_available_bytes, fmt_bytes, host_available_bytes
from ..progress import ProgressFn, Throttle
from ..types import (AUTO_GRID_RES, Anchor, Camera, Conditions, Force, Gaussians, InitialVelocity, Material, SimResult,
                     SimSettings, Torque)
from .fill import fill_particles
from .mpm import Domain, MPMSolver, estimate_bytes, resolve_device
from .regions import select

log = logging.getLogger("physmotion.sim")


class _ForceSchedule:
    """Per-particle external forces as a sum of time-windowed terms."""

    def __init__(self, n: int):
        self.n = n
        self.terms: list[tuple[float, float, np.ndarray]] = []

    def add(self, t0: float, t1: float, f: np.ndarray) -> None:
        self.terms.append((t0, t1, f))

    def active(self, t: float) -> tuple[int, ...]:
        return tuple(i for i, (t0, t1, _) in enumerate(self.terms) if t0 <= t < t1)

    def total(self, active: tuple[int, ...]) -> np.ndarray:
        f = np.zeros((self.n, 3), np.float64)
        for i in active:
            f += self.terms[i][2]
        return f

    def next_edge(self, t: float) -> float:
        edges = [e for t0, t1, _ in self.terms for e in (t0, t1) if e > t + 1e-12]
        return min(edges) if edges else math.inf


def simulate(
    gaussians: Gaussians,
    material: Material,
    conditions: Conditions | None = None,
    settings: SimSettings | None = None,
    *,
    camera: Optional[Camera] = None,
    progress: Optional[ProgressFn] = None,
) -> SimResult:
    """Simulate the object the Gaussians describe and return its trajectory.

    The solid the Gaussians enclose is filled with particles (``fill_particles``); each Gaussian
    follows the particle of its voxel. Time steps are chosen every substep from the CFL limits;
    frames are recorded at t = k / fps for k = 0..frames-1.
    """
    settings = settings or SimSettings()
    settings.validate()
    conditions = conditions or Conditions()
    material.validate()
    gaussians.validate("the Gaussians to simulate")
    unsupported = [type(c).__name__ for c in conditions if isinstance(c, (Torque, Anchor))]
    if unsupported:
        raise InputError(f"Condition(s) {sorted(set(unsupported))} are not supported by this version of the "
                         "simulator yet; remove them or use Force / InitialVelocity / Ground / Walls / Gravity")
    device = resolve_device(settings.device)
    t_start = time.perf_counter()

    means = gaussians.means.detach().float().cpu().numpy()
    size = float(np.max(means.max(0) - means.min(0)))
    if not (size > 0):
        raise InputError("The Gaussians have zero extent; the object must have a size to simulate")
    grid_res = settings.grid_res or AUTO_GRID_RES["cuda" if device.startswith("cuda") else "cpu"]
    dx = size / grid_res
    per_axis = round(settings.particles_per_cell ** (1 / 3))
    parts = fill_particles(gaussians, dx / per_axis, max_particles=settings.max_particles, seed=settings.seed)
    if parts.spacing > dx / per_axis * 1.001:
        log.warning("particle count capped at max_particles=%d: particle spacing raised from %.4g m to %.4g m",
                    settings.max_particles, dx / per_axis, parts.spacing)
    x0 = parts.x
    ground = conditions.ground()
    domain = Domain.around(x0.min(0), x0.max(0), dx, settings.domain_margin, ground)

    bound = np.unique(parts.binding)
    need = estimate_bytes(x0.shape[0], domain.dims, settings.frames, bound.shape[0])
    dev_free = device_available_bytes(device)
    if device.startswith("cuda"):
        if need["device"] > 0.9 * dev_free:
            raise InputError(f"The simulation needs about {fmt_bytes(need['device'])} on {device} but only "
                             f"{fmt_bytes(dev_free)} is free. Lower grid_res, particles_per_cell or domain_margin.")
        host_need = need["host"]
    else:
        host_need = need["host"] + need["device"]
    if host_need > 0.8 * host_available_bytes():
        raise InputError(f"The simulation needs about {fmt_bytes(host_need)} of RAM but only "
                         f"{fmt_bytes(host_available_bytes())} is available. Lower frames, grid_res or "
                         "particles_per_cell.")

    # Initial velocities.
    v0 = np.zeros_like(x0)
    for iv in conditions.of(InitialVelocity):
        sel = select(iv.region, x0, parts.object_id, camera, "initial velocity")
        mass = parts.volume[sel]
        com = (x0[sel] * mass[:, None]).sum(0) / mass.sum()
        v0[sel] += np.asarray(iv.velocity) + np.cross(np.asarray(iv.angular_velocity), x0[sel] - com)

    solver = MPMSolver(x0, parts.volume, np.zeros(x0.shape[0], np.int64), [material], domain,
                       gravity=conditions.gravity(), ground=ground, walls=conditions.walls(),
                       cfl=settings.cfl, device=device, v0=v0)

    schedule = _ForceSchedule(x0.shape[0])
    for force in conditions.of(Force):
        sel = select(force.region, x0, parts.object_id, camera, "force")
        m = solver.mass_np[sel].astype(np.float64)
        f = np.zeros((x0.shape[0], 3))
        f[sel] = np.asarray(force.vector)[None, :] * (m / m.sum())[:, None]
        schedule.add(force.t_start, force.t_end, f)

    frames = settings.frames
    frame_dt = 1.0 / settings.fps
    xs = torch.empty(frames, bound.shape[0], 3)
    Fs = torch.empty(frames, bound.shape[0], 3, 3)
    xs[0] = torch.from_numpy(x0[bound])
    Fs[0] = torch.eye(3)
    tick = Throttle(progress, 0.2)
    tick(0, frames - 1)
    active = None
    t_loop = time.perf_counter()
    for k in range(1, frames):
        t_frame = k * frame_dt
        while solver.t < t_frame - 1e-9:
            now_active = schedule.active(solver.t)
            if now_active != active:
                solver.set_external_forces(schedule.total(now_active))
                active = now_active
            dt = min(solver.stable_dt(), t_frame - solver.t, schedule.next_edge(solver.t) - solver.t)
            solver.substep(dt, frame=k)
            if solver.substeps % 64 == 0:
                tick(k - 1, frames - 1)  # lets Cancel act mid-frame on slow frames
        xs[k] = torch.from_numpy(solver.positions()[bound])
        Fs[k] = torch.from_numpy(solver.deformation()[bound])
        tick(k, frames - 1)

    loop_s = time.perf_counter() - t_loop
    remap = np.full(x0.shape[0], -1, np.int64)
    remap[bound] = np.arange(bound.shape[0])
    wall = time.perf_counter() - t_start
    stats = {
        "device": device,
        "particles": int(x0.shape[0]),
        "particle_spacing": parts.spacing,
        "dx": dx,
        "grid_res": grid_res,
        "grid_dims": list(domain.dims),
        "substeps": solver.substeps,
        "dt_min": solver.dt_min,
        "dt_max": solver.dt_max,
        "wall_time_s": wall,
        "kernel_load_s": solver.kernel_load_s,
        "stepping_s": loop_s,
        "particle_substeps_per_s": x0.shape[0] * solver.substeps / max(loop_s, 1e-9),
    }
    log.info("simulated %d frames: %d particles, %d substeps, %.1fs", frames, x0.shape[0], solver.substeps, wall)
    return SimResult(
        rest=gaussians.detach(),
        times=torch.arange(frames, dtype=torch.float64) * frame_dt,
        x=xs,
        F=Fs,
        binding=torch.from_numpy(remap[parts.binding]),
        rest_particles=torch.from_numpy(x0[bound]),
        material=material,
        stats=stats,
    )
