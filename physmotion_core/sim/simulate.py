"""simulate(): Gaussians + materials + conditions → a trajectory (SimResult)."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Callable, Optional, Sequence, Union

import numpy as np
import torch

from ..errors import InputError
from ..memory import device_available_bytes, host_available_bytes
from ..progress import ProgressFn, Throttle, duration_words
from ..types.camera import Camera
from ..types.conditions import Anchor, Conditions, InitialVelocity, ObjectContact, Torque
from ..types.gaussians import Gaussians
from ..types.material import Material
from ..types.results import SimResult
from ..types.settings import SimSettings
from .fill import FilledObjects, fill_objects
from .mpm import MAX_TORQUES, PRELOAD_MAX_SAG, PRELOAD_MAX_STRAIN, PRELOAD_MODELS, Domain, MPMSolver, cpu_chunks, estimate_bytes, resolve_device
from .regions import select
from .schedule import LoadSchedule

log = logging.getLogger("physmotion.sim")

REST_FRAMES = 3  # consecutive still frames before a scene counts as at rest
FLOWING_MODELS = ("drucker_prager", "snow", "viscoplastic", "fluid")  # splats keep their orientation


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
                peak_accel: float, peak_speed: float, load_speed: float = 0.0, start_speed: float = 0.0) -> str:
    """Refuse, before the first substep, a run whose step would be above the stability limit or
    whose substep count per frame would exceed ``settings.max_substeps_per_frame``. ``peak_speed``: what
    anchors drive; ``load_speed``: what the forces and torques would reach (``LoadSchedule.impulse_speed``);
    ``start_speed``: the fastest initial velocity (the solver starts from it too). Returns what sets the
    step, in words (for ``_Pace``'s forecast)."""
    dt0, why = solver.estimate_dt(peak_accel, max(peak_speed, load_speed))
    stiff = max(materials, key=lambda m: m.wave_speed())
    speeds = {"moving at": start_speed, "driven by an anchor at": peak_speed,
              "pushed by the forces and torques (their impulse over the mass, if nothing stopped them) to": load_speed}
    how, fastest = max(speeds.items(), key=lambda kv: kv[1])
    cause = {"wave speed": f"material '{stiff.name}' (E={stiff.E:.3g} Pa, ρ={stiff.density:.3g} kg/m³) carries waves at "
                           f"{stiff.wave_speed():.3g} m/s",
             "acceleration": f"the forces and torques accelerate it at up to {peak_accel:.3g} m/s²",
             "viscosity": "a fluid's viscosity limits the explicit step"}[why]
    fix = "Lower E or the force, raise the density, lower grid_res"
    if why == "wave speed" and fastest > stiff.wave_speed():
        cause = f"the bodies are {how} about {fastest:.3g} m/s"
        fix = ("Lower the speeds, the forces or torques, or their duration, lower grid_res" if "forces" in how
               else "Lower the speeds, lower grid_res")
    if settings.fixed_dt and settings.fixed_dt > dt0 * (1 + 1e-6):
        raise InputError(f"fixed_dt={settings.fixed_dt:.3g} s is above the stable step {dt0:.3g} s for this scene: "
                         f"{cause} on a grid of dx={solver.domain.dx:.3g} m (CFL {solver.cfl}). Use fixed_dt <= "
                         f"{dt0:.3g}, or 0 for the adaptive step.")
    step = min(dt0, frame_dt / settings.min_substeps, settings.fixed_dt or math.inf)
    per_frame = math.ceil(frame_dt / step)
    if per_frame > settings.max_substeps_per_frame:
        raise InputError(f"This run would need about {per_frame} substeps per frame (step {step:.3g} s), more than "
                         f"max_substeps_per_frame={settings.max_substeps_per_frame}: {cause} on a grid of "
                         f"dx={solver.domain.dx:.3g} m. {fix}, or raise max_substeps_per_frame if you mean to wait.")
    return f"{cause} on a grid of dx={solver.domain.dx:.3g} m"


def _object_ids(gaussians: Gaussians) -> tuple[np.ndarray, np.ndarray]:
    """Each Gaussian's object id, and the objects (0..n-1)."""
    obj_ids = (gaussians.object_ids.cpu().numpy().astype(np.int64) if gaussians.object_ids is not None
               else np.zeros(len(gaussians), np.int64))
    objects = np.unique(obj_ids)
    if objects.min() < 0 or not np.array_equal(objects, np.arange(objects.max() + 1)):
        raise InputError(f"object_ids must number the objects 0..n-1 without gaps; got {objects.tolist()}")
    return obj_ids, objects


def _object_contact(conditions: Conditions, n_objects: int) -> ObjectContact:
    """How the objects meet: on velocity fields of their own (ObjectContact), except with anchors,
    whose passes hold one shared field (the objects then stick where they touch; logged)."""
    oc = conditions.object_contact()
    if n_objects > 1 and oc.contact != "shared" and conditions.of(Anchor):
        log.warning("This scene anchors an object: all %d objects move on one shared velocity field, so they stick "
                    "where they touch instead of bouncing off each other", n_objects)
        return ObjectContact("shared", oc.friction)
    return oc


#: The simulation box reaches past the camera's view by this many object sizes on each side and above (at the
#: depths the object spans), so that an object the user sees moving leaves the frame before it meets the box's
#: walls. Before (domain_margin alone, one object size around it), a small ball in a wide photo stopped dead in
#: mid-frame at the wall 77 mm away, and the thrown_ball template's rubber ball bounced back off it.
VIEW_ROOM = 1.0
#: At most this many grid nodes for the view's room (the node velocities are dense: 12 bytes each per velocity
#: field, 44 on CUDA with the accumulators): beyond it the room past the margin box grows less, evenly.
VIEW_MAX_NODES = 8_000_000


def view_box(x: np.ndarray, camera: Camera, room: float) -> Optional[tuple[np.ndarray, np.ndarray]]:
    """The world box (lo, hi) around what ``camera`` sees at the camera depths the points ``x`` span, grown by
    ``room`` m on every side; None when a point lies behind the camera's near plane."""
    pts = torch.as_tensor(np.asarray(x, np.float32))
    _, z = camera.project(pts)
    z_lo, z_hi = float(z.min()), float(z.max())
    if not (math.isfinite(z_lo) and math.isfinite(z_hi)) or z_lo <= max(float(camera.near), 0.0):
        return None
    W, H = float(camera.width), float(camera.height)
    uv = torch.tensor([[0.0, 0.0], [W, 0.0], [0.0, H], [W, H]] * 2)
    depth = torch.tensor([z_lo] * 4 + [z_hi] * 4)
    corners = camera.unproject(uv, depth).double().numpy()
    return corners.min(0) - room, corners.max(0) + room


def view_domain(domain: Domain, x: np.ndarray, camera: Camera) -> Domain:
    """``domain`` (the margin box around the particles ``x``) grown by whole cells (the grid under the object stays
    where it was) to hold the camera's view at the object's depths plus VIEW_ROOM object sizes (``view_box``),
    within VIEW_MAX_NODES nodes (all sides' room then shrinks by the same share). The floor stays the ground.
    Unchanged without a view (the object behind the camera)."""
    lo, hi = x.min(0).astype(np.float64), x.max(0).astype(np.float64)
    view = view_box(x, camera, VIEW_ROOM * float(np.max(hi - lo)))
    if view is None:
        return domain
    add_lo = np.ceil(np.maximum(domain.lo - view[0], 0.0) / domain.dx).astype(np.int64)
    add_hi = np.ceil(np.maximum(view[1] - domain.hi, 0.0) / domain.dx).astype(np.int64)
    if domain.ground_node >= 0:
        add_lo[1] = 0

    def grown(f: float) -> Domain:
        a, b = np.floor(f * add_lo).astype(np.int64), np.floor(f * add_hi).astype(np.int64)
        return Domain(origin=domain.origin - a * domain.dx, dx=domain.dx,
                      dims=tuple(int(d + p + q) for d, p, q in zip(domain.dims, a, b)),
                      ground_node=domain.ground_node)

    out = grown(1.0)
    if int(np.prod(out.dims)) > VIEW_MAX_NODES:
        a, b = 0.0, 1.0
        for _ in range(30):
            f = 0.5 * (a + b)
            a, b = (f, b) if int(np.prod(grown(f).dims)) <= VIEW_MAX_NODES else (a, f)
        out = grown(a)
        log.info("the simulation box covers %.0f%% of the way to the camera's view past the margin (%d nodes at most)",
                 100 * a, VIEW_MAX_NODES)
    return out


@dataclass
class Resolution:
    """The grid and particle spacing of a scene: ``grid_res`` cells across its largest extent."""

    grid_res: int
    dx: float
    spacing: float

    @classmethod
    def of(cls, means: np.ndarray, settings: SimSettings, device: str) -> "Resolution":
        size = float(np.max(means.max(0) - means.min(0)))
        if not (size > 0):
            raise InputError("The Gaussians have zero extent; the object must have a size to simulate")
        grid_res = settings.resolved_grid_res(device)
        dx = size / grid_res
        per_axis = round(settings.particles_per_cell ** (1 / 3))
        return cls(grid_res, dx, dx / per_axis)


def check_memory(num_particles: int, domain: Domain, frames: int, recorded: int, device: str,
                 make_room: Optional[Callable[[int, str], None]] = None, fields: int = 1) -> None:
    """Refuse a run whose arrays would not fit (device memory on CUDA, RAM for the rest); on CUDA,
    ``make_room(bytes, device)`` may free memory first."""
    need = estimate_bytes(num_particles, domain.dims, frames, recorded, chunks=cpu_chunks(num_particles, device),
                          fields=fields)
    if make_room is not None and device.startswith("cuda"):
        make_room(int(need["device"]), device)
    dev_free = device_available_bytes(device)
    if device.startswith("cuda"):
        if need["device"] > 0.9 * dev_free:
            from ..memory import over_limit_message

            raise InputError(f"The simulation {over_limit_message(need['device'], dev_free, 0.9, 'memory on ' + device)}. "
                             "Lower grid_res, particles_per_cell or domain_margin, or free GPU memory.")
        host_need = need["host"]
    else:
        host_need = need["host"] + need["device"]
    have = host_available_bytes()
    if host_need > 0.8 * have:
        from ..memory import over_limit_message

        raise InputError(f"The simulation {over_limit_message(host_need, have, 0.8)}. Lower frames, grid_res or "
                         "particles_per_cell, or free memory (close other programs or models).")


@dataclass
class InitialState:
    """What the Conditions set per particle before the first substep."""

    v0: np.ndarray  # (P,3) initial velocities
    C0: Optional[np.ndarray]  # (P,3,3) affine velocities of the initial spins (None: no spin)
    anchor_sel: list  # each Anchor's particles (P,) bool
    body: np.ndarray  # (P,) rigid body index, -1 for deformable particles
    torque_mask: np.ndarray  # (P,) bit k: in torque k's region


def initial_state(conditions: Conditions, parts: FilledObjects, materials: Sequence[Material],
                  objects: np.ndarray, region: Callable) -> InitialState:
    x0, volume, particle_obj = parts.x, parts.volume, parts.particle_object
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
    def held(a):
        try:
            return region(a.region, "anchor")
        except InputError:
            if not a.optional:
                raise
            # A hold chosen by the run (the frame's edge, support.py) that no particle lies in: nothing to hold.
            log.warning("the hold at the frame's edge covers no particle of the object; nothing is held there")
            return np.zeros(len(x0), bool)

    anchor_sel = [held(a) for a in conditions.of(Anchor)]
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
    return InitialState(v0, C0, anchor_sel, body, torque_mask)


#: A body held still from the start (a frame edge, an anchor) cannot tip or slide away under its own weight: its
#: relaxation may bend it this far (a fraction of its height) before the preload is given up; its strain limit
#: (PRELOAD_MAX_STRAIN) still decides whether the photo's shape with that stress is near equilibrium.
PRELOAD_MAX_SAG_HELD = 0.3


def held_at_start(conditions: Conditions, init: InitialState) -> Optional[np.ndarray]:
    """The particles the anchors hold still from the start, (P,) bool; None when an anchor active at the start
    moves (a hand that drags: no equilibrium to start in)."""
    held = np.zeros(len(init.v0), bool)
    for a, sel in zip(conditions.of(Anchor), init.anchor_sel):
        if a.t_start > 0 or not sel.any():
            continue
        if np.any(np.asarray(a.velocity, np.float64) != 0):
            return None
        held |= sel
    return held


def preload_plan(settings: SimSettings, conditions: Conditions, parts: FilledObjects, materials: Sequence[Material],
                 init: InitialState, dx: float) -> Optional[tuple[float, float]]:
    """Whether the scene starts in equilibrium under gravity (``MPMSolver.preload``), and if so the
    (height m, shear wave speed m/s) that set its slowest ringing: the tallest body's height above what
    holds it up (the ground; for a body held still from the start, as a photo's frame edge holds what it
    cuts, its largest extent) and the slowest shear speed. It applies when ``settings.preload`` is on,
    gravity pulls downwards, every object is an elastic solid (PRELOAD_MODELS) whose lowest particle lies
    within a cell of the ground or that an anchor holds still from the start, and nothing moves or is
    rigid at the start. Otherwise None (no cost): sand, snow, clay, fluids and plastic bodies flow to their
    own rest, rigid bodies carry no stress, a body in the air or thrown starts unloaded, and a body dragged
    by a moving anchor has no rest to start from. The relaxation holds the anchored particles
    (``simulate`` sets them first)."""
    ground = conditions.ground()
    g = np.asarray(conditions.gravity(), np.float64)
    if not settings.preload or not g[1] < 0 or len(parts.x) == 0:
        return None
    if np.any(init.body >= 0) or init.C0 is not None or np.any(init.v0 != 0):
        return None
    held = held_at_start(conditions, init)
    if held is None:
        return None
    height, speed = 0.0, math.inf
    for o, mat in enumerate(materials):
        mine = parts.particle_object == o
        x = parts.x[mine]
        if mat.model not in PRELOAD_MODELS or len(x) == 0:
            return None
        if held[mine].any():
            height = max(height, float(np.ptp(x, axis=0).max()))
        elif ground is not None and x[:, 1].min() - ground.height <= dx:
            height = max(height, float(x[:, 1].max() - ground.height))
        else:
            return None
        speed = min(speed, math.sqrt(mat.mu / mat.density))
    return (height, speed) if height > 0 and speed > 0 else None


class _Recorder:
    """The recorded particles' positions, deformation gradients and plastic state per frame, and
    the energy per frame."""

    def __init__(self, solver: MPMSolver, frames: int, recorded: np.ndarray, x0: np.ndarray):
        self.solver = solver
        self.recorded = recorded
        n_rec = recorded.shape[0]
        self.x = torch.empty(frames, n_rec, 3)
        self.F = torch.empty(frames, n_rec, 3, 3)
        self.plastic = torch.empty(frames, n_rec)
        self.x[0] = torch.from_numpy(x0[recorded])
        self.F[0] = torch.eye(3)
        self.plastic[0] = torch.from_numpy(solver.plastic_state()[recorded])
        self.energy = {"kinetic": [], "potential": [], "work": []}
        # With a gravity preload the photo is the loaded state: frames carry F relative to it.
        pre = getattr(solver, "F_preload", None)
        self.F_rest_inv = None if pre is None else np.linalg.inv(pre[recorded].astype(np.float64))

    def record_energy(self) -> None:
        kin, pot = self.solver.energy()
        self.energy["kinetic"].append(kin)
        self.energy["potential"].append(pot)
        self.energy["work"].append(self.solver.work)

    def record(self, k: int) -> None:
        """Frame k is the solver's state now."""
        s, rec = self.solver, self.recorded
        self.x[k] = torch.from_numpy(s.positions()[rec])
        F = s.deformation()[rec]
        if self.F_rest_inv is not None:
            F = np.matmul(F.astype(np.float64), self.F_rest_inv).astype(np.float32)
        self.F[k] = torch.from_numpy(F)
        self.plastic[k] = torch.from_numpy(s.plastic_state()[rec])
        self.record_energy()

    def repeat(self, k: int) -> None:
        """Frame k repeats frame k - 1 (the scene is at rest)."""
        self.x[k], self.F[k], self.plastic[k] = self.x[k - 1], self.F[k - 1], self.plastic[k - 1]
        for key in self.energy:
            self.energy[key].append(self.energy[key][-1])


#: Progress steps per frame: the bar moves within a frame too (a stiff material's frame can take minutes).
PROGRESS_PER_FRAME = 100
#: Substeps run in launches of about this many seconds (``MPMSolver.advance``): progress and Cancel between them.
LAUNCH_SECONDS = 0.2
#: After this many seconds of stepping the run's pace is known well enough to forecast its length; a forecast of
#: PACE_WARN_S or more is said once (a warning: what sets the step and what makes it quicker).
PACE_CHECK_S = 3.0
PACE_WARN_S = 120.0


def progress_total(frames: int) -> int:
    """The progress total of a simulation of ``frames`` frames (PROGRESS_PER_FRAME steps per frame after frame 0)."""
    return max(1, (frames - 1) * PROGRESS_PER_FRAME)


class _Pace:
    """The frame loop's progress as a fraction of the simulated time (``PROGRESS_PER_FRAME`` steps per frame),
    and once, after PACE_CHECK_S s of stepping, a forecast of how long the whole run takes at the pace so far:
    a warning when it is PACE_WARN_S or more, with what sets the step (``cause``) and what makes it quicker."""

    def __init__(self, solver: MPMSolver, frames: int, frame_dt: float, tick: Throttle, cause: str = "",
                 on_pace: Optional[Callable[[str], None]] = None):
        self.solver, self.frames, self.frame_dt, self.tick, self.cause = solver, frames, frame_dt, tick, cause
        self.on_pace = on_pace
        self.total = progress_total(frames)
        self.t0, self.sim_t0 = time.perf_counter(), float(solver.t)
        self.steps0 = int(solver.substeps)
        self.forecast_s: Optional[float] = None

    def __call__(self, k: int) -> None:
        """During frame ``k`` (from 1): report where the solver's clock is, and forecast once."""
        t = float(self.solver.t)
        within = min(max((t - (k - 1) * self.frame_dt) / self.frame_dt, 0.0), 1.0)
        self.tick(min((k - 1) * PROGRESS_PER_FRAME + int(within * PROGRESS_PER_FRAME + 1e-6), self.total), self.total)
        if self.forecast_s is None:
            self._forecast(t)

    def _forecast(self, t: float) -> None:
        wall = time.perf_counter() - self.t0
        done = t - self.sim_t0
        if wall < PACE_CHECK_S or done <= 0.0:
            return
        end = (self.frames - 1) * self.frame_dt
        self.forecast_s = wall * (end - self.sim_t0) / done
        if self.forecast_s < PACE_WARN_S:
            return
        steps = int(self.solver.substeps) - self.steps0
        dt = done / max(steps, 1)
        from ..feedback import QUICKER_RUN

        msg = (f"At the pace so far this simulation takes about {duration_words(self.forecast_s)} ({wall:.1f} s for "
               f"{done:.3g} s of {end - self.sim_t0:.3g} s simulated, in steps of {dt:.2g} s"
               f"{': ' + self.cause if self.cause else ''}). For a quicker run: {QUICKER_RUN}.")
        log.warning("%s", msg)
        if self.on_pace is not None:
            self.on_pace(msg)


def _advance_frame(solver: MPMSolver, schedule: LoadSchedule, state: dict, t_frame: float, k: int,
                   progress: Callable[[], None]) -> None:
    """Substeps up to ``t_frame``, handing the solver each change of the active loads."""
    solver.begin_frame()
    while solver.t < t_frame - 1e-9:
        now_active = schedule.active(solver.t)
        if now_active != state["active"]:
            schedule.apply(solver, now_active)
            state["active"] = now_active
        # Substeps run on the device up to the frame's end or the next change of the forces; the
        # step is chosen there from the CFL limits (MPMSolver.advance). Between launches (a fraction
        # of a second each) the progress callback lets Cancel act mid-frame.
        solver.advance(min(t_frame, schedule.next_edge(solver.t)), frame=k, progress=progress,
                       launch_seconds=LAUNCH_SECONDS)


def run_frames(solver: MPMSolver, schedule: LoadSchedule, settings: SimSettings, recorded: np.ndarray,
               x0: np.ndarray, progress: Optional[ProgressFn], cause: str = "",
               on_pace: Optional[Callable[[str], None]] = None) -> tuple[_Recorder, Optional[int], float]:
    """The frame loop: frames at t = k / fps; once the scene is at rest (REST_FRAMES still frames
    with no load still to come) later frames repeat its state. Progress goes by the simulated time
    (``_Pace``, which also forecasts a long run once; ``cause``: what sets the step). Returns the recording, the
    frame the rest began (or None) and the seconds the loop took."""
    frames = settings.frames
    frame_dt = 1.0 / settings.fps
    rec = _Recorder(solver, frames, recorded, x0)
    tick = Throttle(progress, 0.2)
    pace = _Pace(solver, frames, frame_dt, tick, cause, on_pace)
    tick(0, pace.total)
    state = {"active": None}
    still_frames = 0
    rest_from = None
    rec.record_energy()
    t_loop = time.perf_counter()
    for k in range(1, frames):
        if rest_from is not None:
            rec.repeat(k)
            tick(k * PROGRESS_PER_FRAME, pace.total)
            continue
        _advance_frame(solver, schedule, state, k * frame_dt, k, lambda: pace(k))
        still = settings.rest_speed > 0 and solver.frame_rms < settings.rest_speed
        still_frames = still_frames + 1 if still and not schedule.pending(solver.t) else 0
        if still_frames >= REST_FRAMES:
            rest_from = k  # at rest: later frames repeat this state without substepping
            log.info("scene at rest from frame %d (RMS speed %.2g m/s): substepping stops", k, solver.frame_rms)
        rec.record(k)
        tick(k * PROGRESS_PER_FRAME, pace.total)
    return rec, rest_from, time.perf_counter() - t_loop


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
    on_start: Optional[Callable] = None,
    on_pace: Optional[Callable[[str], None]] = None,
) -> SimResult:
    """Simulate the object(s) the Gaussians describe and return their trajectory.

    Each object (``gaussians.object_ids``; one object if absent) is filled with particles on its
    own (``fill_particles``) and gets its material (``material`` may be one per object). Every
    Gaussian follows a weighted blend of its nearest particles' local affine maps. Time steps come from the CFL limits every
    substep; frames are recorded at t = k / fps for k = 0..frames-1. ``record_all`` keeps every
    particle's trajectory (default: only those carrying Gaussians). ``make_room(bytes, device)`` is
    called on CUDA with the device memory the run needs before it checks that it fits (ComfyUI's
    nodes free cached models there). ``on_start(facts)`` is called once the objects are filled and
    weighed, before the first substep, with a ``feedback.BodyFacts`` (particle positions and masses):
    what the user is told before the wait. ``on_pace(message)`` is called (besides a logged warning) when the
    pace of the first seconds says the run takes minutes or more (``_Pace``).

    The steps: fill the objects with particles (``fill_objects``), check the run fits in memory
    (``check_memory``), turn the Conditions into per-particle arrays (``initial_state``) and a
    compiled ``LoadSchedule``, refuse a run the step limits make too long (``_check_cost``), then
    the frame loop (``run_frames``).
    """
    settings = settings or SimSettings()
    settings.validate()
    conditions = conditions or Conditions()
    gaussians.validate("the Gaussians to simulate")
    obj_ids, objects = _object_ids(gaussians)
    materials = _as_materials(material, len(objects))
    device = resolve_device(settings.device)
    t_start = time.perf_counter()

    means = gaussians.means.detach().float().cpu().numpy()
    res = Resolution.of(means, settings, device)
    ground = conditions.ground()
    # A rigid body's outer particles follow its surface (no lattice flats: a ball or a wheel rolls; fill._conform).
    # Deformable bodies keep the lattice, whose equal spacing their stress needs (docs/accuracy.md, "Rolling").
    parts = fill_objects(gaussians, obj_ids, objects, res.spacing, res.dx, settings.max_particles, settings.seed,
                         ground, conform=[m.model == "rigid" for m in materials])
    x0 = parts.x
    domain = Domain.around(x0.min(0), x0.max(0), res.dx, settings.domain_margin, ground)
    if camera is not None:
        domain = view_domain(domain, x0, camera)
    recorded = np.arange(len(x0)) if record_all else np.unique(parts.neighbours)
    object_contact = _object_contact(conditions, len(objects))
    fields = len(objects) if len(objects) > 1 and object_contact.contact != "shared" else 1
    check_memory(x0.shape[0], domain, settings.frames, recorded.shape[0], device, make_room, fields)

    def region(r, what):
        return select(r, x0, parts.particle_object, camera, what)

    init = initial_state(conditions, parts, materials, objects, region)
    solver = MPMSolver(x0, parts.volume, parts.particle_object, materials, domain, gravity=conditions.gravity(),
                       ground=ground, walls=conditions.walls(), cfl=settings.cfl, device=device, v0=init.v0,
                       C0=init.C0, body=init.body, torque_mask=init.torque_mask, transfer=settings.transfer,
                       graph={"auto": None, "on": True, "off": False}[settings.graph],
                       threads=settings.cpu_threads, objects=parts.particle_object, object_contact=object_contact,
                       ground_gap=settings.ground_gap if settings.ground_gap >= 0 else None)
    schedule = LoadSchedule.compile(conditions, x0, solver.mass_np, init.torque_mask, init.anchor_sel, region)
    frame_dt = 1.0 / settings.fps
    cause = _check_cost(solver, settings, materials, frame_dt, schedule.peak_accel(solver.mass_np),
                schedule.peak_anchor_speed(), schedule.impulse_speed(x0, solver.mass_np),
                float(np.linalg.norm(np.asarray(init.v0), axis=1).max()) if init.v0 is not None and len(x0) else 0.0)
    solver.set_limits(max_dt=min(frame_dt / settings.min_substeps, settings.fixed_dt or math.inf),
                      max_frame_substeps=settings.max_substeps_per_frame)
    plan = preload_plan(settings, conditions, parts, materials, init, res.dx)
    pre_tick = Throttle(progress, 0.2)
    sag = PRELOAD_MAX_SAG
    if plan is not None:
        held = held_at_start(conditions, init)
        if held.any():  # the relaxation holds what holds the body up (the run's schedule sets them again)
            solver.set_anchors(held, np.zeros((len(x0), 3)))
            sag = PRELOAD_MAX_SAG_HELD
    preload = (solver.preload(*plan, max_sag=sag, on_step=lambda: pre_tick(0, progress_total(settings.frames)))
               if plan is not None else None)
    if preload is not None and preload["applied"]:
        log.info("preload: the bodies settled under gravity in %d substeps (%.2f s, %.1f periods, sag %.3g m)",
                 preload["substeps"], preload["seconds"], preload["periods"], preload["sag"])
    elif preload is not None:
        # Info, not a warning: the run goes on as it always did (stress-free start), and the user has
        # nothing to change; `-v` shows it, and stats["preload"] records it.
        log.info("preload given up after %d substeps (%.2f s): under gravity the bodies %s; they start "
                 "stress-free", preload["substeps"], preload["seconds"],
                 f"moved {preload['sag']:.3g} m (they tip or slide)" if preload["sag"] > sag * plan[0]
                 else f"strain by {preload['strain']:.0%} (too far from the photo for its stress to hold it)"
                 if preload["strain"] > PRELOAD_MAX_STRAIN else "did not settle")
    if on_start is not None:
        from ..feedback import BodyFacts

        on_start(BodyFacts(x0, solver.mass_np.astype(np.float64), float(res.dx), len(objects) == 1))

    rec, rest_from, loop_s = run_frames(solver, schedule, settings, recorded, x0, progress, cause, on_pace)
    wall = time.perf_counter() - t_start
    stats = _run_stats(solver, settings, res, domain, len(objects), rest_from, wall, loop_s, rec.energy)
    stats["preload"] = preload
    log.info("simulated %d frames: %d particles, %d substeps, %.1fs (%d thread%s)", settings.frames, x0.shape[0],
             solver.substeps, wall, solver.threads, "" if solver.threads == 1 else "s")
    from ..feedback import piece_labels

    result = _result(gaussians, parts, recorded, materials, rec, frame_dt, stats)
    # which separate body each recorded particle is part of (labelled on all particles: the recorded ones
    # alone are too sparse inside), for the "a piece left the frame" warning
    if len(objects) == 1:
        result.particle_piece = torch.from_numpy(piece_labels(x0, res.dx)[recorded])
    return result


def _run_stats(solver: MPMSolver, settings: SimSettings, res: Resolution, domain: Domain, n_objects: int,
               rest_from: Optional[int], wall: float, loop_s: float, energy: dict) -> dict:
    return {
        "device": solver.device,
        "particles": int(solver.n),
        "objects": int(n_objects),
        "particle_spacing": float(res.spacing),
        "dx": res.dx,
        "grid_res": res.grid_res,
        "grid_dims": list(domain.dims),
        "substeps": solver.substeps,
        "dt_min": solver.dt_min,
        "dt_max": solver.dt_max,
        "rest_from_frame": rest_from,
        "wall_time_s": wall,
        "kernel_load_s": solver.kernel_load_s,
        "stepping_s": loop_s,
        "particle_substeps_per_s": solver.n * solver.substeps / max(loop_s, 1e-9),
        "mass_kg": float(solver.mass_np.astype(np.float64).sum()),
        "energy": energy,  # per frame: kinetic, gravitational potential, cumulative external work (J)
        "transfer": settings.transfer,
        "graph": solver.use_graph,
        "launches": solver.launches,  # host round trips (one per launch of substeps)
        "graph_captures": solver.graph_captures,
        "cpu_chunks": solver.chunks,  # particle chunks of p2g / g2p (1 on CUDA); fixed by the scene
        "threads": solver.threads,  # CPU threads that ran them
    }


def _result(gaussians: Gaussians, parts: FilledObjects, recorded: np.ndarray, materials: Sequence[Material],
            rec: _Recorder, frame_dt: float, stats: dict) -> SimResult:
    remap = np.full(parts.x.shape[0], -1, np.int64)
    remap[recorded] = np.arange(recorded.shape[0])
    obj = parts.particle_object[recorded]
    return SimResult(
        rest=gaussians.detach(),
        times=torch.arange(rec.x.shape[0], dtype=torch.float64) * frame_dt,
        x=rec.x,
        F=rec.F,
        binding=torch.from_numpy(remap[parts.binding]),
        neighbours=torch.from_numpy(remap[parts.neighbours]),
        weights=torch.from_numpy(parts.weights),
        rest_particles=torch.from_numpy(parts.x[recorded]),
        material=materials[0],
        materials=materials,
        stats=stats,
        plastic=rec.plastic,
        particle_object=torch.from_numpy(obj),
        rotation_free=torch.from_numpy(np.array([m.model in FLOWING_MODELS for m in materials])[obj]),
        liquid=torch.from_numpy(np.array([m.model == "fluid" for m in materials])[obj]),
    )
