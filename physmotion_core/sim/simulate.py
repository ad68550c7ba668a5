"""simulate(): Gaussians + materials + conditions → a trajectory (SimResult)."""

from __future__ import annotations

import logging
import math
import time
from typing import Callable, Optional, Sequence, Union

import numpy as np
import torch

from ..errors import InputError, SimulationError
from ..memory import device_available_bytes, fmt_bytes, host_available_bytes
from ..progress import ProgressFn, Throttle
from ..types import (Anchor, Camera, Conditions, Force, Gaussians, InitialVelocity, Material, SimResult,
                     SimSettings, Torque)
from .fill import fill_particles
from .mpm import MAX_TORQUES, Domain, MPMSolver, cpu_chunks, estimate_bytes, resolve_device
from .regions import select

log = logging.getLogger("physmotion.sim")

REST_FRAMES = 3  # consecutive still frames before a scene counts as at rest
FLOWING_MODELS = ("drucker_prager", "snow", "viscoplastic", "fluid")  # splats keep their orientation


class _Schedule:
    """Time-windowed terms (forces, torques): which are active at t, and when that next changes."""

    def __init__(self):
        self.windows: list[tuple[float, float]] = []

    def add(self, t0: float, t1: float) -> int:
        self.windows.append((t0, t1))
        return len(self.windows) - 1

    def active(self, t: float) -> tuple[int, ...]:
        return tuple(i for i, (t0, t1) in enumerate(self.windows) if t0 <= t < t1)

    def next_edge(self, t: float) -> float:
        edges = [e for w in self.windows for e in w if e > t + 1e-12]
        return min(edges) if edges else math.inf

    def pending(self, t: float) -> bool:
        """Is any term active now or still to come?"""
        return any(t1 > t + 1e-12 for _, t1 in self.windows)


def _as_materials(material, n_objects: int) -> list[Material]:
    mats = list(material) if isinstance(material, (list, tuple)) else [material]
    if not mats:
        raise InputError("At least one material is needed")
    if len(mats) == 1 and n_objects > 1:
        mats = mats * n_objects
    if len(mats) != n_objects:
        raise InputError(f"The scene has {n_objects} objects but {len(mats)} materials were given; give one "
                         "material per object (Combine Objects pairs them up)")
    for m in mats:
        if not isinstance(m, Material):
            raise InputError(f"Not a Material: {m!r}")
        m.validate()
    return mats


def _check_cost(solver: MPMSolver, settings: SimSettings, materials: Sequence[Material], frame_dt: float,
                peak_accel: float, peak_speed: float) -> None:
    """Refuse, before the first substep, a run whose step would be above the stability limit or
    whose substep count per frame would exceed ``settings.max_substeps_per_frame``."""
    dt0, why = solver.estimate_dt(peak_accel, peak_speed)
    stiff = max(materials, key=lambda m: m.wave_speed())
    cause = {"wave speed": f"material '{stiff.name}' (E={stiff.E:.3g} Pa, ρ={stiff.density:.3g} kg/m³) carries waves at "
                           f"{stiff.wave_speed():.3g} m/s",
             "acceleration": f"the forces and torques accelerate it at up to {peak_accel:.3g} m/s²",
             "viscosity": "a fluid's viscosity limits the explicit step"}[why]
    if settings.fixed_dt and settings.fixed_dt > dt0 * (1 + 1e-6):
        raise InputError(f"fixed_dt={settings.fixed_dt:.3g} s is above the stable step {dt0:.3g} s for this scene: "
                         f"{cause} on a grid of dx={solver.domain.dx:.3g} m (CFL {solver.cfl}). Use fixed_dt <= "
                         f"{dt0:.3g}, or 0 for the adaptive step.")
    step = min(dt0, frame_dt / settings.min_substeps, settings.fixed_dt or math.inf)
    per_frame = math.ceil(frame_dt / step)
    if per_frame > settings.max_substeps_per_frame:
        raise InputError(f"This run would need about {per_frame} substeps per frame (step {step:.3g} s), more than "
                         f"max_substeps_per_frame={settings.max_substeps_per_frame}: {cause} on a grid of "
                         f"dx={solver.domain.dx:.3g} m. Lower E or the force, raise the density, lower grid_res, or "
                         "raise max_substeps_per_frame if you mean to wait.")


def simulate(
    gaussians: Gaussians,
    material: Union[Material, Sequence[Material]],
    conditions: Conditions | None = None,
    settings: SimSettings | None = None,
    *,
    camera: Optional[Camera] = None,
    progress: Optional[ProgressFn] = None,
    record_all: bool = False,
    make_room: Optional[Callable[[int, str], None]] = None,
) -> SimResult:
    """Simulate the object(s) the Gaussians describe and return their trajectory.

    Each object (``gaussians.object_ids``; one object if absent) is filled with particles on its
    own (``fill_particles``) and gets its material (``material`` may be one per object). Every
    Gaussian follows a weighted blend of its nearest particles' local affine maps. Time steps come from the CFL limits every
    substep; frames are recorded at t = k / fps for k = 0..frames-1. ``record_all`` keeps every
    particle's trajectory (default: only those carrying Gaussians). ``make_room(bytes, device)`` is
    called on CUDA with the device memory the run needs before it checks that it fits (ComfyUI's
    nodes free cached models there).
    """
    settings = settings or SimSettings()
    settings.validate()
    conditions = conditions or Conditions()
    gaussians.validate("the Gaussians to simulate")
    obj_ids = (gaussians.object_ids.cpu().numpy().astype(np.int64) if gaussians.object_ids is not None
               else np.zeros(len(gaussians), np.int64))
    objects = np.unique(obj_ids)
    if objects.min() < 0 or not np.array_equal(objects, np.arange(objects.max() + 1)):
        raise InputError(f"object_ids must number the objects 0..n-1 without gaps; got {objects.tolist()}")
    materials = _as_materials(material, len(objects))
    device = resolve_device(settings.device)
    t_start = time.perf_counter()

    means = gaussians.means.detach().float().cpu().numpy()
    size = float(np.max(means.max(0) - means.min(0)))
    if not (size > 0):
        raise InputError("The Gaussians have zero extent; the object must have a size to simulate")
    grid_res = settings.resolved_grid_res(device)
    dx = size / grid_res
    per_axis = round(settings.particles_per_cell ** (1 / 3))
    spacing = dx / per_axis

    # Fill each object on its own, so the gap between two objects is never filled in.
    xs, vols, obj_of, binding = [], [], [], np.zeros(len(gaussians), np.int64)
    neighbours = np.zeros((len(gaussians), 1), np.int64)
    weights = np.ones((len(gaussians), 1), np.float32)
    offset = 0
    budget = settings.max_particles
    ground = conditions.ground()
    if ground is not None and float(means[:, 1].min()) < ground.height - 0.5 * dx:
        raise InputError(f"The object reaches below the ground (lowest Gaussian centre y={float(means[:, 1].min()):.4f} m, "
                         f"ground at {ground.height:.4f} m). Raise the object or lower the ground.")
    for o in objects:
        sel = np.nonzero(obj_ids == o)[0]
        g_o = gaussians.subset(torch.from_numpy(sel))
        g_o.object_ids = None
        share = max(1, int(budget * len(sel) / len(gaussians)))
        # Splats resting on the ground reach below it; the particles start at the ground.
        parts = fill_particles(g_o, spacing, max_particles=share, seed=settings.seed + int(o),
                               floor=None if ground is None else ground.height)
        if parts.spacing > spacing * 1.001:
            log.warning("object %d: particle count capped (max_particles=%d): spacing raised from %.4g m to %.4g m",
                        o, settings.max_particles, spacing, parts.spacing)
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
    x0 = np.concatenate(xs)
    volume = np.concatenate(vols)
    particle_obj = np.concatenate(obj_of)

    domain = Domain.around(x0.min(0), x0.max(0), dx, settings.domain_margin, ground)
    recorded = np.arange(len(x0)) if record_all else np.unique(neighbours)
    need = estimate_bytes(x0.shape[0], domain.dims, settings.frames, recorded.shape[0],
                          chunks=cpu_chunks(x0.shape[0], device))
    if make_room is not None and device.startswith("cuda"):
        make_room(int(need["device"]), device)
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

    def region(r, what):
        return select(r, x0, particle_obj, camera, what)

    # Initial velocities (ω about the region's centre of mass), with the velocity gradient of that
    # rigid motion as the particles' affine velocity C = [ω]×: APIC carries an affine field to the
    # grid and back exactly, so the body starts with exactly v0 + ω0 × r (with C = 0 the first
    # transfer would average the spin away at the body's edges, ~2 % of it).
    v0 = np.zeros_like(x0)
    C0 = None
    for iv in conditions.of(InitialVelocity):
        sel = region(iv.region, "initial velocity")
        mass = volume[sel]
        com = (x0[sel] * mass[:, None]).sum(0) / mass.sum()
        w = np.asarray(iv.angular_velocity, np.float64)
        v0[sel] += np.asarray(iv.velocity) + np.cross(w, x0[sel] - com)
        if np.any(w != 0):
            C0 = np.zeros((len(x0), 3, 3)) if C0 is None else C0
            C0[sel] += np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    anchors = conditions.of(Anchor)
    anchor_sel = [region(a.region, "anchor") for a in anchors]
    anchored = np.zeros(len(x0), bool)
    for sel in anchor_sel:
        anchored |= sel
    # Rigid objects: one body each.
    body = np.full(len(x0), -1, np.int64)
    rigid_objects = [o for o in objects if materials[o].model == "rigid"]
    for b, o in enumerate(rigid_objects):
        body[particle_obj == o] = b
    if np.any(anchored & (body >= 0)):
        raise InputError("An anchor region covers a rigid object; anchor a deformable object, or give the rigid "
                         "object no motion instead (it will rest on the ground)")
    torques = conditions.of(Torque)
    if len(torques) > MAX_TORQUES:
        raise InputError(f"At most {MAX_TORQUES} torques are supported; got {len(torques)}")
    torque_mask = np.zeros(len(x0), np.int64)
    for k, tq in enumerate(torques):
        torque_mask[region(tq.region, "torque")] |= 1 << k

    solver = MPMSolver(x0, volume, particle_obj, materials, domain, gravity=conditions.gravity(), ground=ground,
                       walls=conditions.walls(), cfl=settings.cfl, device=device, v0=v0, C0=C0,
                       body=body, torque_mask=torque_mask, transfer=settings.transfer,
                       graph={"auto": None, "on": True, "off": False}[settings.graph],
                       threads=settings.cpu_threads)

    forces = conditions.of(Force)
    f_terms, schedule = [], _Schedule()
    for force in forces:
        sel = region(force.region, "force")
        m = solver.mass_np[sel].astype(np.float64)
        f = np.zeros((x0.shape[0], 3))
        f[sel] = np.asarray(force.vector)[None, :] * (m / m.sum())[:, None]
        f_terms.append(f)
        schedule.add(force.t_start, force.t_end)
    torque_bounds = []
    for k, tq in enumerate(torques):
        sel = (torque_mask >> k) & 1 == 1
        m = solver.mass_np[sel].astype(np.float64)
        r = x0[sel] - (x0[sel] * m[:, None]).sum(0) / m.sum()
        inertia = np.eye(3) * (m * (r * r).sum(1)).sum() - (r.T * m) @ r
        alpha = np.linalg.norm(np.linalg.solve(inertia, np.asarray(tq.vector)))
        torque_bounds.append(alpha * float(np.linalg.norm(r, axis=1).max()))
        schedule.add(tq.t_start, tq.t_end)
    for a in anchors:
        schedule.add(a.t_start, a.t_end)
    n_ft = len(forces) + len(torques)
    peak_accel = sum(float((np.linalg.norm(f, axis=1) / solver.mass_np).max()) for f in f_terms) + sum(torque_bounds)
    peak_anchor = max([float(np.linalg.norm(a.velocity)) for a in anchors], default=0.0)
    frame_dt = 1.0 / settings.fps
    _check_cost(solver, settings, materials, frame_dt, peak_accel, peak_anchor)
    solver.set_limits(max_dt=min(frame_dt / settings.min_substeps, settings.fixed_dt or math.inf),
                      max_frame_substeps=settings.max_substeps_per_frame)

    def apply_schedule(active: tuple[int, ...]) -> None:
        f = np.zeros((x0.shape[0], 3))
        for i in active:
            if i < len(forces):
                f += f_terms[i]
        solver.set_external_forces(f)
        taus = np.zeros((max(len(torques), 1), 3))
        bound = 0.0
        for i in active:
            if len(forces) <= i < n_ft:
                taus[i - len(forces)] = torques[i - len(forces)].vector
                bound += torque_bounds[i - len(forces)]
        solver.set_torques(taus, bound)
        held = np.zeros(len(x0), bool)
        velocity = np.zeros((len(x0), 3))
        for i in active:
            if i >= n_ft:
                a = i - n_ft
                held |= anchor_sel[a]
                velocity[anchor_sel[a]] = anchors[a].velocity
        solver.set_anchors(held, velocity)

    frames = settings.frames
    n_rec = recorded.shape[0]
    xs_t = torch.empty(frames, n_rec, 3)
    Fs_t = torch.empty(frames, n_rec, 3, 3)
    plastic_t = torch.empty(frames, n_rec)
    xs_t[0] = torch.from_numpy(x0[recorded])
    Fs_t[0] = torch.eye(3)
    plastic_t[0] = torch.from_numpy(solver.plastic_state()[recorded])
    tick = Throttle(progress, 0.2)
    tick(0, frames - 1)
    active = None
    still_frames = 0
    rest_from = None
    energy = {"kinetic": [], "potential": [], "work": []}

    def record_energy() -> None:
        kin, pot = solver.energy()
        energy["kinetic"].append(kin)
        energy["potential"].append(pot)
        energy["work"].append(solver.work)

    record_energy()
    t_loop = time.perf_counter()
    for k in range(1, frames):
        t_frame = k * frame_dt
        if rest_from is None:
            solver.begin_frame()
            while solver.t < t_frame - 1e-9:
                now_active = schedule.active(solver.t)
                if now_active != active:
                    apply_schedule(now_active)
                    active = now_active
                # Substeps run on the device up to the frame's end or the next change of the forces;
                # the step is chosen there from the CFL limits (MPMSolver.advance). Between launches
                # (a fraction of a second each) the progress callback lets Cancel act mid-frame.
                solver.advance(min(t_frame, schedule.next_edge(solver.t)), frame=k,
                               progress=lambda: tick(k - 1, frames - 1))
            still = settings.rest_speed > 0 and solver.frame_rms < settings.rest_speed
            still_frames = still_frames + 1 if still and not schedule.pending(solver.t) else 0
            if still_frames >= REST_FRAMES:
                rest_from = k  # at rest: later frames repeat this state without substepping
                log.info("scene at rest from frame %d (RMS speed %.2g m/s): substepping stops", k, solver.frame_rms)
            xs_t[k] = torch.from_numpy(solver.positions()[recorded])
            Fs_t[k] = torch.from_numpy(solver.deformation()[recorded])
            plastic_t[k] = torch.from_numpy(solver.plastic_state()[recorded])
            record_energy()
        else:
            xs_t[k], Fs_t[k], plastic_t[k] = xs_t[k - 1], Fs_t[k - 1], plastic_t[k - 1]
            for key in energy:
                energy[key].append(energy[key][-1])
        tick(k, frames - 1)
    loop_s = time.perf_counter() - t_loop

    remap = np.full(x0.shape[0], -1, np.int64)
    remap[recorded] = np.arange(n_rec)
    wall = time.perf_counter() - t_start
    stats = {
        "device": device,
        "particles": int(x0.shape[0]),
        "objects": int(len(objects)),
        "particle_spacing": float(spacing),
        "dx": dx,
        "grid_res": grid_res,
        "grid_dims": list(domain.dims),
        "substeps": solver.substeps,
        "dt_min": solver.dt_min,
        "dt_max": solver.dt_max,
        "rest_from_frame": rest_from,
        "wall_time_s": wall,
        "kernel_load_s": solver.kernel_load_s,
        "stepping_s": loop_s,
        "particle_substeps_per_s": x0.shape[0] * solver.substeps / max(loop_s, 1e-9),
        "mass_kg": float(solver.mass_np.astype(np.float64).sum()),
        "energy": energy,  # per frame: kinetic, gravitational potential, cumulative external work (J)
        "transfer": settings.transfer,
        "graph": solver.use_graph,
        "launches": solver.launches,  # host round trips (one per launch of substeps)
        "graph_captures": solver.graph_captures,
        "cpu_chunks": solver.chunks,  # particle chunks of p2g / g2p (1 on CUDA); fixed by the scene
        "threads": solver.threads,  # CPU threads that ran them
    }
    log.info("simulated %d frames: %d particles, %d substeps, %.1fs (%d thread%s)", frames, x0.shape[0],
             solver.substeps, wall, solver.threads, "" if solver.threads == 1 else "s")
    return SimResult(
        rest=gaussians.detach(),
        times=torch.arange(frames, dtype=torch.float64) * frame_dt,
        x=xs_t,
        F=Fs_t,
        binding=torch.from_numpy(remap[binding]),
        neighbours=torch.from_numpy(remap[neighbours]),
        weights=torch.from_numpy(weights),
        rest_particles=torch.from_numpy(x0[recorded]),
        material=materials[0],
        materials=materials,
        stats=stats,
        plastic=plastic_t,
        particle_object=torch.from_numpy(particle_obj[recorded]),
        rotation_free=torch.from_numpy(np.array([m.model in FLOWING_MODELS for m in materials])[particle_obj[recorded]]),
        liquid=torch.from_numpy(np.array([m.model == "fluid" for m in materials])[particle_obj[recorded]]),
    )
