"""What the user is told before the wait and after it.

Before simulating: the object's mass and material, and what each push, twist or throw will roughly do,
from Newton's laws on the whole body (no simulation): the change of speed Δv = F·Δt / m, whether the
push beats static friction μ·m·g, whether it can tip the object over its base edge (F·h > m·g·b, the
quasi-static tipping condition about the edge it pushes towards), and whether the estimated travel
leaves the frame. These are estimates for a body that stays in one piece; they say what to change when
a push is far too weak or far too strong, so that nobody waits minutes for a video in which nothing
moves, or in which the object flies off screen.

After simulating: a warning when nothing moved visibly, and when the object left the frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from .types.camera import Camera
from .types.conditions import Anchor, Conditions, Force, Ground, InitialVelocity, Torque
from .types.material import Material

#: Below this many pixels of largest motion in the input view, "nothing moved" is reported.
STILL_PX = 1.0
#: The object counts as having left the frame when this fraction of it projects outside the image.
LEFT_FRACTION = 0.5


@dataclass
class BodyFacts:
    """The filled object: particle rest positions (P, 3) and masses (P,) in SI units."""

    x: np.ndarray
    mass: np.ndarray

    @property
    def total_mass(self) -> float:
        return float(self.mass.astype(np.float64).sum())

    @property
    def com(self) -> np.ndarray:
        m = self.mass.astype(np.float64)
        return (self.x.astype(np.float64) * m[:, None]).sum(0) / max(m.sum(), 1e-30)


def body_facts(gaussians, material: Material, settings, ground: Optional[Ground], device: str = "cpu") -> BodyFacts:
    """Fill the object with the simulator's particles (as ``simulate`` will) and weigh them, without
    simulating: what ``generate(preview=True)`` reports."""
    from .sim.fill import fill_objects
    from .sim.simulate import Resolution, _object_ids

    means = gaussians.means.detach().float().cpu().numpy()
    res = Resolution.of(means, settings, device)
    obj_ids, objects = _object_ids(gaussians)
    parts = fill_objects(gaussians, obj_ids, objects, res.spacing, res.dx, settings.max_particles, settings.seed,
                         ground)
    return BodyFacts(parts.x, (parts.volume * float(material.density)).astype(np.float64))


def _fmt_mass(m: float) -> str:
    return f"{m * 1000:.3g} g" if m < 1.0 else f"{m:.3g} kg"


def _window(c, clip_s: float) -> tuple[float, float]:
    t0 = max(0.0, float(c.t_start))
    t1 = min(float(c.t_end), clip_s)
    return t0, max(t0, t1)


def _region_sel(c, facts: BodyFacts, camera: Optional[Camera]) -> np.ndarray:
    from .errors import InputError
    from .sim.regions import select

    try:
        return select(c.region, facts.x, np.zeros(len(facts.x), np.int64), camera, type(c).__name__.lower())
    except InputError:
        return np.ones(len(facts.x), bool)  # reported by the simulation itself, with its own message


def frame_room(facts: BodyFacts, camera: Optional[Camera]) -> Optional[tuple[float, float]]:
    """Metres of free room, at the object's depth, between the object and the frame's left and right
    edges (None without a camera)."""
    if camera is None:
        return None
    pts = torch.from_numpy(facts.x.astype(np.float32))
    uv, z = camera.project(pts)
    com_uv, com_z = camera.project(torch.from_numpy(facts.com.astype(np.float32))[None])
    depth = float(com_z[0])
    if not depth > 0:
        return None
    m_per_px = depth / float(camera.fx)
    u = uv[:, 0].numpy()
    return float(u.min()) * m_per_px, float(camera.width - u.max()) * m_per_px


def forecast(conditions: Conditions, facts: BodyFacts, material: Material, *, clip_s: float,
             camera: Optional[Camera] = None, held: bool = False) -> list[str]:
    """Plain sentences: the mass and material, then what each load will roughly do."""
    m = facts.total_mass
    g = float(np.linalg.norm(conditions.gravity()))
    ground = conditions.ground()
    lines = [f"object: {material.name}, {_fmt_mass(m)} ({len(facts.x)} particles); E = {material.E:.3g} Pa, "
             f"density {material.density:.4g} kg/m³."]
    if m <= 0:
        return lines
    anchored = held or bool(conditions.of(Anchor))
    base_y = float(facts.x[:, 1].min())
    base = facts.x[facts.x[:, 1] <= base_y + 0.05 * max(1e-9, float(np.ptp(facts.x[:, 1])))]
    com = facts.com
    room = frame_room(facts, camera)
    friction_limit = None
    if ground is not None and not anchored:
        friction_limit = {"sticky": math.inf, "slip": 0.0}.get(ground.contact, float(ground.friction) * m * g)
    for k, f in enumerate(conditions.of(Force), 1):
        t0, t1 = _window(f, clip_s)
        dt = t1 - t0
        F = np.asarray(f.vector, np.float64)
        fmag = float(np.linalg.norm(F))
        dv = fmag * dt / m
        head = f"force {k}: {fmag:.3g} N for {dt:.3g} s on {_fmt_mass(m)}: Δv ≈ {dv:.3g} m/s if nothing held it"
        notes = []
        if anchored:
            notes.append("the object is held, so the push bends or shears it rather than moving it away")
        fh = float(math.hypot(F[0], F[2]))
        if ground is not None and not anchored and fh > 1e-12:
            if math.isinf(friction_limit):
                notes.append("the ground is sticky: it will not slide")
            elif fh <= friction_limit:
                notes.append(f"static friction holds up to μ·m·g = {friction_limit:.3g} N, more than its {fh:.3g} N "
                             f"sideways: it will not slide (push harder than {friction_limit:.3g} N or lower the "
                             "friction to make it slide)")
            else:
                notes.append(f"it beats static friction (μ·m·g = {friction_limit:.3g} N): it slides")
            sel = _region_sel(f, facts, camera)
            h = float(facts.x[sel, 1].mean()) - base_y
            d = F[[0, 2]] / fh
            b = float((base[:, [0, 2]] @ d).max() - com[[0, 2]] @ d) if len(base) else 0.0
            need = m * g * max(b, 0.0) / max(h, 1e-9)
            if fh * h > m * g * max(b, 0.0):
                notes.append(f"it can tip over (F·h = {fh * h:.3g} N·m > m·g·b = {m * g * max(b, 0):.3g} N·m)")
            elif fh > 0.3 * need:
                notes.append(f"it rocks but does not tip (tipping needs about {need:.3g} N at that height)")
        if F[1] > m * g and not anchored:
            notes.append(f"it lifts off (upward {F[1]:.3g} N > its weight {m * g:.3g} N)")
        # Travel along x (the frame's width), for a free or sliding body: the push, then coasting to the
        # clip's end (kinetic friction ≈ μ slows it on a friction ground).
        if room is not None and not anchored and abs(F[0]) > 1e-12:
            mu_g = 0.0 if ground is None or ground.contact == "slip" else (
                math.inf if ground.contact == "sticky" else float(ground.friction) * g)
            a = abs(F[0]) / m - mu_g
            if a > 0:
                v = a * dt
                travel = 0.5 * a * dt * dt
                rest = max(0.0, clip_s - t1)
                travel += v * rest if mu_g == 0 else min(v * rest, v * v / (2 * mu_g))
                side = room[1] if F[0] > 0 else room[0]
                if travel > side:
                    notes.append(f"it may leave the frame: about {travel:.3g} m of travel against {side:.3g} m of room "
                                 f"on the {'right' if F[0] > 0 else 'left'} (use a smaller force or a shorter push)")
        lines.append(head + ("; " + "; ".join(notes) if notes else "") + ".")
    for k, tq in enumerate(conditions.of(Torque), 1):
        t0, t1 = _window(tq, clip_s)
        T = np.asarray(tq.vector, np.float64)
        tm = float(np.linalg.norm(T))
        if tm <= 0:
            continue
        sel = _region_sel(tq, facts, camera)
        axis = T / tm
        r = facts.x[sel] - (facts.x[sel] * facts.mass[sel, None]).sum(0) / max(facts.mass[sel].sum(), 1e-30)
        r_perp2 = (r * r).sum(1) - (r @ axis) ** 2
        inertia = float((facts.mass[sel] * r_perp2).sum())
        dw = tm * (t1 - t0) / max(inertia, 1e-30)
        lines.append(f"torque {k}: {tm:.3g} N·m for {t1 - t0:.3g} s about an axis with moment of inertia "
                     f"{inertia:.3g} kg·m²: Δω ≈ {dw:.3g} rad/s ({math.degrees(dw) / 360:.3g} turns per second) if "
                     "nothing resisted it" + ("; it is held, so it twists rather than turns" if anchored else "") + ".")
    for k, iv in enumerate(conditions.of(InitialVelocity), 1):
        v = np.asarray(iv.velocity, np.float64)
        w = np.asarray(iv.angular_velocity, np.float64)
        line = f"throw {k}: starts at {float(np.linalg.norm(v)):.3g} m/s"
        if np.any(w != 0):
            line += f", spinning at {float(np.linalg.norm(w)):.3g} rad/s"
        if room is not None and abs(v[0]) > 0:
            side = room[1] if v[0] > 0 else room[0]
            if abs(v[0]) * clip_s > side and (ground is None or ground.contact == "slip"):
                line += f"; at that speed it leaves the frame within {side / abs(v[0]):.2g} s"
        lines.append(line + ".")
    return lines


@dataclass
class MotionReport:
    """What the clip shows: the largest motion in pixels of the input view, the first frame where most
    of the object was outside the frame (None if never), and the warnings for the user."""

    max_motion_px: float
    left_frame_at: Optional[int]
    warnings: list


def after_run(sim, camera: Camera) -> MotionReport:
    """Warn when nothing moved visibly (largest particle motion under ``STILL_PX`` in the input view,
    frames 1..end against frame 0) and when the object left the frame (``LEFT_FRACTION`` of its
    particles project outside the image or behind the camera)."""
    x = sim.x
    T = int(x.shape[0])
    uv0, _ = camera.project(x[0].float())
    motion = 0.0
    left_at = None
    W, H = float(camera.width), float(camera.height)
    for k in range(1, T):
        uv, z = camera.project(x[k].float())
        motion = max(motion, float((uv - uv0).norm(dim=1).max()) if uv.shape[0] else 0.0)
        outside = (z <= 0) | (uv[:, 0] < 0) | (uv[:, 0] > W) | (uv[:, 1] < 0) | (uv[:, 1] > H)
        if left_at is None and uv.shape[0] and float(outside.float().mean()) >= LEFT_FRACTION:
            left_at = k
    warnings = []
    if T > 1 and motion < STILL_PX:
        warnings.append(f"nothing moved visibly: the largest motion in the video is {motion:.2g} px. The push is too "
                        "weak for this mass and friction (see the forecast above), or the object is held; push "
                        "harder, push longer, lower the friction or the density.")
    if left_at is not None:
        warnings.append(f"the object left the frame: from frame {left_at} ({float(sim.times[left_at]):.2g} s) most "
                        "of it is outside the picture. Use a smaller force, a shorter push, more friction or fewer "
                        "frames.")
    return MotionReport(motion, left_at, warnings)
