"""The accuracy suite: the simulator against analytic or published answers.

Every case returns ``CaseResult`` objects with the measured and expected value, the error, and a
tolerance with the reason for it. ``physmotion validate`` runs them all and writes
docs/accuracy.md; the tests run the cheap ones.
"""

from __future__ import annotations

import math
from typing import Callable, Optional

import numpy as np

from ..types.material import material_preset
from ..sim.mpm import GROUND_GAP, MPMSolver
from ..types.conditions import Ground, ObjectContact
from ..types.material import Material
from .harness import CaseResult, ball, box_domain, lattice, momentum, run_sampled, timed

G = 9.81
FRAME_DT = 1.0 / 24.0
MIN_SUBSTEPS = 8  # simulate()'s default: steps no longer than a frame / 8


def _elastic(E: float, nu: float = 0.3, density: float = 1000.0, damping: float = 0.0,
             model: str = "fixed_corotated") -> Material:
    return Material(name="elastic", model=model, E=E, nu=nu, density=density, damping=damping)


def _solver(x, vol, mat, domain, **kw) -> MPMSolver:
    return MPMSolver(x, vol, np.zeros(len(x), np.int64), [mat], domain, **kw)


# ---------------------------------------------------------------------------------------------
# Ballistics
# ---------------------------------------------------------------------------------------------

@timed
def free_fall(t_end: float = 1.0, max_dt: float = FRAME_DT / MIN_SUBSTEPS) -> CaseResult:
    """A 0.2 m jelly cube falls from rest for ``t_end`` s: the centre of mass drops g t²/2."""
    x, vol = lattice((-0.1, 0.0, -0.1), (0.1, 0.2, 0.1), 0.025)
    drop = 0.5 * G * t_end**2
    dom = box_domain((-0.2, -drop - 0.2, -0.2), (0.2, 0.4, 0.2), 0.05)
    s = _solver(x, vol, _elastic(1e4), dom)
    y0 = momentum(s)[2][1]
    (com,) = run_sampled(s, [t_end], lambda s: momentum(s)[2], max_dt=max_dt)
    measured = y0 - com[1]
    dt_used = t_end / s.substeps
    return CaseResult("free fall", f"drop in {t_end:g} s (m)", measured, drop, measured / drop - 1,
                      tolerance=1.2 * dt_used / t_end + 1e-3,
                      why="symplectic Euler overshoots the drop by g·t·dt/2, a relative dt/t "
                          f"(dt = {dt_used:.2g} s here)",
                      details={"substeps": s.substeps, "dt": dt_used})


@timed
def projectile(t_end: float = 0.5, v0=(1.0, 2.0, 0.5)) -> CaseResult:
    """A cube thrown with v0 under gravity: the centre of mass follows x0 + v0 t + g t²/2."""
    x, vol = lattice((-0.05, 0.0, -0.05), (0.05, 0.1, 0.05), 0.0125)
    v = np.tile(np.asarray(v0, float), (len(x), 1))
    dom = box_domain((-0.2, -1.0, -0.2), (0.8, 1.4, 0.5), 0.025)
    s = _solver(x, vol, _elastic(1e4), dom, v0=v)
    c0 = momentum(s)[2]
    (com,) = run_sampled(s, [t_end], lambda s: momentum(s)[2], max_dt=FRAME_DT / MIN_SUBSTEPS)
    expect = c0 + np.asarray(v0) * t_end + np.array([0.0, -0.5 * G * t_end**2, 0.0])
    travel = np.linalg.norm(expect - c0)
    err = float(np.linalg.norm(com - expect) / travel)
    dt_used = t_end / s.substeps
    return CaseResult("projectile", f"position after {t_end:g} s (m, |error| / distance)",
                      float(np.linalg.norm(com - c0)), float(travel), err,
                      tolerance=1.2 * 0.5 * G * t_end * dt_used / travel + 1e-3,
                      why="the same first-order overshoot as free fall (g·t·dt/2), relative to the distance",
                      details={"substeps": s.substeps})


# ---------------------------------------------------------------------------------------------
# Conservation and rotation
# ---------------------------------------------------------------------------------------------

@timed
def momentum_conservation(t_end: float = 0.4) -> list[CaseResult]:
    """Two spinning jelly cubes collide in free flight (no gravity, walls far away): total linear
    and angular momentum must not change."""
    a, va = lattice((-0.25, -0.05, -0.05), (-0.15, 0.05, 0.05), 0.0125)
    b, vb = lattice((0.15, -0.03, -0.05), (0.25, 0.07, 0.05), 0.0125)
    x = np.concatenate([a, b])
    vol = np.concatenate([va, vb])
    ca, cb = a.mean(0), b.mean(0)
    v = np.concatenate([np.array([1.0, 0.0, 0.0]) + np.cross([0.0, 0.0, 6.0], a - ca),
                        np.array([-1.0, 0.1, 0.0]) + np.cross([3.0, 0.0, 0.0], b - cb)])
    dom = box_domain((-0.6, -0.4, -0.4), (0.6, 0.4, 0.4), 0.025)
    s = _solver(x, vol, _elastic(5e4), dom, v0=v, gravity=(0.0, 0.0, 0.0))
    origin = np.zeros(3)
    p0, l0, _ = momentum(s, origin)
    (p1, l1, _), = run_sampled(s, [t_end], lambda s: momentum(s, origin))
    scale_p = float(np.abs(s.mass_np.astype(np.float64)[:, None] * v).sum())  # Σ m|v|: momentum "size"
    scale_l = float(np.linalg.norm(np.cross(x, s.mass_np.astype(np.float64)[:, None] * v), axis=1).sum())
    ep = float(np.linalg.norm(p1 - p0) / scale_p)
    el = float(np.linalg.norm(l1 - l0) / scale_l)
    details = {"substeps": s.substeps}
    return [
        CaseResult("momentum conservation", "|ΔP| / Σ m|v|", float(np.linalg.norm(p1)), float(np.linalg.norm(p0)),
                   ep, 1e-4, "P2G/G2P conserve momentum exactly; float32 atomics round off ~1e-6 per step",
                   details=details),
        CaseResult("angular momentum conservation", "|ΔL| / Σ |r × m v|", float(np.linalg.norm(l1)),
                   float(np.linalg.norm(l0)), el, 1e-4,
                   "APIC conserves L (with the particles' affine part) exactly in exact arithmetic; "
                   "float32 round-off over a few hundred steps", details=details),
    ]


def _fit_omega(x: np.ndarray, v: np.ndarray, m: np.ndarray) -> np.ndarray:
    """The angular velocity ω minimising Σ m |v − V − ω × r|² (least squares rigid fit)."""
    com = (x * m[:, None]).sum(0) / m.sum()
    V = (v * m[:, None]).sum(0) / m.sum()
    r = x - com
    inertia = np.eye(3) * (m * (r * r).sum(1)).sum() - (r.T * m) @ r
    L = (m[:, None] * np.cross(r, v - V)).sum(0)
    return np.linalg.solve(inertia, L), inertia


@timed
def torque_spin_up(t_end: float = 0.4, tau=(0.0, 0.004, 0.0)) -> list[CaseResult]:
    """A 0.1 m cube in free flight under a constant torque: L = τ t, ω = I⁻¹ τ t (rigid and elastic)."""
    out = []
    for model in ("rigid", "elastic"):
        x, vol = lattice((-0.05, -0.05, -0.05), (0.05, 0.05, 0.05), 0.00625)
        dom = box_domain((-0.25, -0.25, -0.25), (0.25, 0.25, 0.25), 0.0125)
        mat = material_preset("rigid") if model == "rigid" else _elastic(2e5)
        body = np.zeros(len(x), np.int64) if model == "rigid" else None
        s = MPMSolver(x, vol, np.zeros(len(x), np.int64), [mat], dom, gravity=(0.0, 0.0, 0.0), body=body,
                      torque_mask=np.ones(len(x), np.int64))
        m = s.mass_np.astype(np.float64)
        r = x - x.mean(0)
        inertia = np.eye(3) * (m * (r * r).sum(1)).sum() - (r.T * m) @ r
        alpha = np.linalg.norm(np.linalg.solve(inertia, tau))
        s.set_torques(np.asarray([tau]), alpha * float(np.linalg.norm(r, axis=1).max()))
        if model == "rigid":
            (state,) = run_sampled(s, [t_end], lambda s: (s.positions().astype(np.float64),
                                                         s.velocities().astype(np.float64)))
            omega, _ = _fit_omega(state[0], state[1], m)
            expect = np.linalg.solve(inertia, np.asarray(tau) * t_end)
            quantity, tol, why = (f"ω after {t_end:g} s (rad/s)", 1e-4,
                                  "exact rigid motion; float32 round-off")
        else:
            # A deforming body's ω is not one number; its angular momentum is: L = τ t exactly.
            (omega,) = run_sampled(s, [t_end], lambda s: momentum(s)[1])
            expect = np.asarray(tau) * t_end
            quantity, tol, why = (f"angular momentum after {t_end:g} s (N·m·s)", 1e-4,
                                  "the torque's forces have zero sum and moment exactly τ; float32 round-off")
        err = float(np.linalg.norm(omega - expect) / np.linalg.norm(expect))
        out.append(CaseResult(f"spin-up under a torque ({model})", quantity, float(np.linalg.norm(omega)),
                              float(np.linalg.norm(expect)), err, tol, why, details={"substeps": s.substeps}))
    return out


# ---------------------------------------------------------------------------------------------
# Free rotation of rigid bodies: Euler's equations
# ---------------------------------------------------------------------------------------------

def _skew(w) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def euler_reference(inertia: np.ndarray, omega0, times, h: float = 2e-4) -> list[tuple[np.ndarray, np.ndarray]]:
    """A torque-free rigid body integrated independently of the simulator, in float64: Euler's
    equations I ω̇ = (I ω) × ω in the body frame and Ṙ = R [ω]×, by classical Runge–Kutta (RK4) at
    steps of ``h`` (local error ~ (h|ω|)⁵, under 1e-12 here), R re-orthonormalised each step.
    ``inertia`` is the body-frame tensor (the rest pose's; R(0) = I). Returns (R, ω in the world
    frame) at each of ``times`` (ascending)."""
    I = np.asarray(inertia, np.float64)
    Iinv = np.linalg.inv(I)

    def rate(R, w):
        return R @ _skew(w), Iinv @ np.cross(I @ w, w)

    R, w, t, out = np.eye(3), np.asarray(omega0, np.float64).copy(), 0.0, []
    for ts in times:
        while t < ts - 1e-13:
            k = min(h, ts - t)
            a = rate(R, w)
            b = rate(R + 0.5 * k * a[0], w + 0.5 * k * a[1])
            c = rate(R + 0.5 * k * b[0], w + 0.5 * k * b[1])
            d = rate(R + k * c[0], w + k * c[1])
            R = R + k / 6 * (a[0] + 2 * b[0] + 2 * c[0] + d[0])
            w = w + k / 6 * (a[1] + 2 * b[1] + 2 * c[1] + d[1])
            u, _, vt = np.linalg.svd(R)
            R = u @ vt
            t += k
        out.append((R.copy(), R @ w))
    return out


def quat_matrix(q) -> np.ndarray:
    """Rotation matrix of a quaternion in Warp's (x, y, z, w) order."""
    x, y, z, w = (float(a) for a in q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def rotation_angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """The angle (rad) of the rotation taking Ra to Rb (well conditioned near zero)."""
    return 2.0 * math.asin(min(1.0, float(np.linalg.norm(Ra - Rb)) / (2.0 * math.sqrt(2.0))))


def elliptic_k(k: float) -> float:
    """Complete elliptic integral of the first kind K(k) (modulus k), by the arithmetic-geometric mean."""
    a, b = 1.0, math.sqrt(1.0 - k * k)
    while abs(a - b) > 1e-15 * a:
        a, b = 0.5 * (a + b), math.sqrt(a * b)
    return math.pi / (2.0 * a)


def _rigid_box(size=(0.3, 0.2, 0.1), spacing: float = 0.0125, omega=(3.0, 1.0, 2.0), margin: float = 0.3):
    """A free rigid box (no gravity, walls ``margin`` m beyond its reach) given the spin ``omega``."""
    half = 0.5 * np.asarray(size, float)
    x, vol = lattice(-half, half, spacing)
    reach = float(np.linalg.norm(half)) + margin
    dom = box_domain((-reach,) * 3, (reach,) * 3, 2 * spacing)
    c = x.mean(0)
    s = MPMSolver(x, vol, np.zeros(len(x), np.int64), [material_preset("rigid")], dom, gravity=(0.0, 0.0, 0.0),
                  v0=np.cross(np.asarray(omega, float), x - c), body=np.zeros(len(x), np.int64))
    m = s.mass_np.astype(np.float64)
    r = x - c
    inertia = np.eye(3) * (m * (r * r).sum(1)).sum() - (r.T * m) @ r
    return s, m, inertia


def _visible(s: MPMSolver, m: np.ndarray) -> tuple[np.ndarray, float]:
    """Angular momentum Σ m (x − c) × v and kinetic energy of the particles as they move (float64)."""
    x = s.positions().astype(np.float64)
    v = s.velocities().astype(np.float64)
    c = (x * m[:, None]).sum(0) / m.sum()
    return (m[:, None] * np.cross(x - c, v)).sum(0), 0.5 * float((m * (v * v).sum(1)).sum())


@timed
def rigid_free_rotation(t_end: float = 1.0, omega=(3.0, 1.0, 2.0)) -> list[CaseResult]:
    """A 0.3 x 0.2 x 0.1 m rigid box spun about a non-principal axis in free flight: its angular
    momentum is constant and its orientation follows Euler's equations (float64 reference)."""
    s, m, inertia = _rigid_box(omega=omega)
    L0, K0 = _visible(s, m)
    ((L1, K1), q), = run_sampled(s, [t_end], lambda s: (_visible(s, m), s.body_state()[1][0]),
                                 max_dt=FRAME_DT / MIN_SUBSTEPS)
    (R_ref, _), = euler_reference(inertia, omega, [t_end])
    err_l = float(np.linalg.norm(L1 - L0) / np.linalg.norm(L0))
    err_deg = math.degrees(rotation_angle(quat_matrix(q), R_ref))
    details = {"substeps": s.substeps, "dt": t_end / s.substeps, "kinetic_energy_drift": K1 / K0 - 1}
    return [
        CaseResult("torque-free rigid box, angular momentum", f"|ΔL| / |L| after {t_end:g} s, "
                   "L = Σ m (x − c) × v", float(np.linalg.norm(L1)), float(np.linalg.norm(L0)), err_l, 1e-4,
                   "L is kept in the world frame and every step of the rotation is an exact flow that keeps it; "
                   "what is left is float32 round-off of the particles' positions and velocities", details=details),
        CaseResult("torque-free rigid box, orientation", f"angle to Euler's equations after {t_end:g} s (°)",
                   err_deg, 0.0, err_deg, 1.0,
                   "second-order splitting of the free-body motion (error ~ (ω dt)² ω t, ~1e-4° here) against "
                   "a float64 RK4 reference; 1° is what a viewer could see", absolute=True, details=details),
    ]


def _axis_turn(axis, angle: float) -> np.ndarray:
    """Rotation matrix about unit ``axis`` by ``angle`` (Rodrigues)."""
    k = _skew(np.asarray(axis, float) / np.linalg.norm(axis))
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


@timed
def symmetric_top(t_end: float = 1.0, omega=(1.0, 0.0, 5.0)) -> CaseResult:
    """A free rigid square plate (0.2 x 0.2 x 0.1 m: I1 = I2 < I3) spun off its symmetry axis: it
    precesses about L at |L| / I1 while turning about its own axis at L3 (1/I3 − 1/I1), so
    R(t) = Rot(L̂, |L| t / I1) · Rot(e3, L3 (1/I3 − 1/I1) t) in closed form (the two motions commute)."""
    s, m, inertia = _rigid_box(size=(0.2, 0.2, 0.1), omega=omega)
    w = np.asarray(omega, float)
    L = inertia @ w
    I1, I3 = float(inertia[0, 0]), float(inertia[2, 2])
    (q,), = run_sampled(s, [t_end], lambda s: s.body_state()[1], max_dt=FRAME_DT / MIN_SUBSTEPS)
    R_exact = _axis_turn(L, np.linalg.norm(L) * t_end / I1) @ _axis_turn((0.0, 0.0, 1.0),
                                                                        L[2] * (1 / I3 - 1 / I1) * t_end)
    deg = math.degrees(rotation_angle(quat_matrix(q), R_exact))
    return CaseResult("symmetric top (rigid plate), precession", f"angle to the closed-form motion after {t_end:g} s (°)",
                      deg, 0.0, deg, 0.01,
                      "the rotation step's splitting is exact for a symmetric top (its axial part vanishes); "
                      "float32 round-off over ~200 steps", absolute=True,
                      details={"substeps": s.substeps, "precession_rate": float(np.linalg.norm(L) / I1)})


@timed
def tennis_racket(spin: float = 6.0, wobble: float = 0.06) -> CaseResult:
    """The same box spun about its intermediate axis (y) with a small spin about its major axis (z):
    it flips over (the Dzhanibekov effect). With ω = (0, Ω, ε) the spin about y is at its maximum
    and, from the elliptic-function solution of Euler's equations (Landau & Lifshitz, Mechanics
    §37), first passes through zero after t = K(k) sqrt(I1 I2 I3 / ((I3 − I2)(L² − 2 E I1))),
    k² = (I2 − I1)(2 E I3 − L²) / ((I3 − I2)(L² − 2 E I1))."""
    omega = np.array([0.0, spin, wobble])
    # A coarse lattice (384 particles) is enough: the reference uses the same particles' inertia.
    s, m, inertia = _rigid_box(omega=omega, spacing=0.025)
    I1, I2, I3 = np.diag(inertia)
    L2 = float(np.sum((np.diag(inertia) * omega) ** 2))
    E2 = float(np.sum(np.diag(inertia) * omega ** 2))  # 2E
    k2 = (I2 - I1) * (E2 * I3 - L2) / ((I3 - I2) * (L2 - E2 * I1))
    t_flip = elliptic_k(math.sqrt(k2)) * math.sqrt(I1 * I2 * I3 / ((I3 - I2) * (L2 - E2 * I1)))
    times, wy = [], []
    while s.t < 1.3 * t_flip:
        s.substep(min(s.stable_dt(), FRAME_DT / MIN_SUBSTEPS))
        _, q, _, w = s.body_state()
        times.append(s.t)
        wy.append(float((quat_matrix(q[0]).T @ w[0].astype(np.float64))[1]))  # body frame
    t, wy = np.asarray(times), np.asarray(wy)
    crossing = _crossing_times(t, wy)
    measured = float(crossing[0]) if len(crossing) else math.nan
    (R_ref, w_ref), = euler_reference(inertia, omega, [t_flip])
    return CaseResult("tennis-racket flip (rigid box about its intermediate axis)",
                      "time of the first reversal of the spin about the intermediate axis (s)",
                      measured, t_flip, measured / t_flip - 1, 0.05,
                      "the flip time depends on ln(Ω/ε) and so magnifies every error in the motion; 5 % is the "
                      "issue's bound (measured within ~0.1 %)",
                      details={"substeps": s.substeps,
                               # the float64 reference's body-frame spin about y at the analytic time: ~0
                               "reference_omega_y_at_t_flip": float((R_ref.T @ w_ref)[1])})


@timed
def rigid_free_fall(t_end: float = 1.0) -> list[CaseResult]:
    """A rigid box falls from rest, and another is thrown: the centre moves x0 + v0 t + g t²/2
    exactly (gravity integrated at the half step), at the simulator's default step and at an odd one."""
    out = []
    for label, max_dt, v0 in (("free fall", FRAME_DT / MIN_SUBSTEPS, (0.0, 0.0, 0.0)),
                              ("projectile", 1.0 / 7.0 / 3.0, (1.0, 2.0, 0.5))):
        x, vol = lattice((-0.05, -0.03, -0.04), (0.05, 0.03, 0.04), 0.01)
        dom = box_domain((-0.3, -5.2, -0.3), (1.3, 1.3, 0.9), 0.02)
        s = MPMSolver(x, vol, np.zeros(len(x), np.int64), [material_preset("rigid")], dom,
                      v0=np.tile(np.asarray(v0, float), (len(x), 1)), body=np.zeros(len(x), np.int64))
        c0 = s.body_state()[0][0].astype(np.float64)
        (c1,), = run_sampled(s, [t_end], lambda s: s.body_state()[0].astype(np.float64), max_dt=max_dt)
        expect = c0 + np.asarray(v0) * t_end + np.array([0.0, -0.5 * G * t_end**2, 0.0])
        travel = float(np.linalg.norm(expect - c0))
        err = float(np.linalg.norm(c1 - expect) / travel)
        out.append(CaseResult(f"rigid {label}", f"position after {t_end:g} s (m, |error| / distance; "
                              f"steps ≤ {max_dt * 1e3:.2g} ms)", float(np.linalg.norm(c1 - c0)), travel, err, 1e-3,
                              "the rigid path integrates constant acceleration exactly (gravity at the half step); "
                              "0.1 % leaves room for float32 round-off", details={"substeps": s.substeps}))
    return out


def _best_rotation(r0: np.ndarray, r1: np.ndarray, m: np.ndarray) -> np.ndarray:
    """The rotation R minimising Σ m |R r0 − r1|² (Kabsch), for centred point sets."""
    U, _, Vt = np.linalg.svd((r0 * m[:, None]).T @ r1)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


@timed
def elastic_tumbling(t_end: float = 0.5, E: float = 5e4, omega=(3.0, 1.0, 2.0)) -> list[CaseResult]:
    """A jelly box (0.3 x 0.2 x 0.1 m, E = 5e4 Pa) spun about a non-principal axis in free flight.

    APIC conserves the particles' angular momentum together with their affine part,
    L = Σ m (x − c) × v + ½ m dx² ω_C (ω_C the spin in C, D = dx²/4): each particle carries the spin
    inertia ½ m dx² of the grid's kernel, so the body tumbles as a body of inertia I + ½ M dx² 𝟙, and
    the visible part Σ m (x − c) × v trades angular momentum with the affine part as ω turns. The case
    checks the total (1e-4), the visible part against that exchange (predicted from the float64
    Euler solution with APIC's inertia), and the orientation against the same solution."""
    half = np.array([0.15, 0.1, 0.05])
    spacing = 0.0125
    dx = 2 * spacing
    x, vol = lattice(-half, half, spacing)
    reach = float(np.linalg.norm(half)) + 0.15
    dom = box_domain((-reach,) * 3, (reach,) * 3, dx)
    w0 = np.asarray(omega, float)
    c = x.mean(0)
    s = _solver(x, vol, _elastic(E), dom, gravity=(0.0, 0.0, 0.0), v0=np.cross(w0, x - c),
                C0=np.tile(_skew(w0), (len(x), 1, 1)))
    m = s.mass_np.astype(np.float64)
    M = float(m.sum())
    r0 = x - c
    inertia = np.eye(3) * (m * (r0 * r0).sum(1)).sum() - (r0.T * m) @ r0
    spin_inertia = 0.5 * M * dx * dx
    Lv0, _ = _visible(s, m)
    Lt0 = momentum(s)[1]

    def observe(s):
        xs = s.positions().astype(np.float64)
        com = (xs * m[:, None]).sum(0) / M
        return _visible(s, m)[0], momentum(s)[1], _best_rotation(r0, xs - com, m)

    (Lv, Lt, R), = run_sampled(s, [t_end], observe, max_dt=FRAME_DT / MIN_SUBSTEPS)
    (R_apic, w_apic), = euler_reference(inertia + spin_inertia * np.eye(3), w0, [t_end])
    (R_pts, _), = euler_reference(inertia, w0, [t_end])
    drift = float(np.linalg.norm(Lv - Lv0) / np.linalg.norm(Lv0))
    predicted = float(spin_inertia * np.linalg.norm(w_apic - w0) / np.linalg.norm(Lv0))
    deg = math.degrees(rotation_angle(R, R_apic))
    details = {"substeps": s.substeps, "visible_drift": drift, "predicted_exchange": predicted,
               "angle_to_euler_point_inertia_deg": math.degrees(rotation_angle(R, R_pts)),
               "spin_inertia_share": spin_inertia / float(np.linalg.eigvalsh(inertia)[0])}
    return [
        CaseResult("tumbling elastic box, APIC angular momentum", f"|ΔL| / |L| after {t_end:g} s (with the affine part)",
                   float(np.linalg.norm(Lt)), float(np.linalg.norm(Lt0)), float(np.linalg.norm(Lt - Lt0) /
                                                                               np.linalg.norm(Lt0)), 1e-4,
                   "APIC conserves it exactly in exact arithmetic; float32 round-off", details=details),
        CaseResult("tumbling elastic box, visible angular momentum", f"|ΔL_visible| / |L| after {t_end:g} s "
                   "(expected: the exchange with the affine part, ½ M dx² |ω(t) − ω0| / |L|)", drift, predicted,
                   drift - predicted, 1e-3,
                   "the visible part moves by what the affine part takes (dx² scaling: docs/accuracy.md); 1e-3 "
                   "covers the elastic body's stretch under its spin (measured ≤ 3e-4)", absolute=True,
                   details=details),
        CaseResult("tumbling elastic box, orientation", f"angle to Euler's equations with APIC's inertia "
                   f"I + ½ M dx² after {t_end:g} s (°)", deg, 0.0, deg, 0.5,
                   "a soft body stretches under its spin and its inertia wobbles with it (0.22° at E = 5e4 Pa, "
                   "0.05° at 2e5)", absolute=True, details=details),
    ]


# ---------------------------------------------------------------------------------------------
# Elastic waves and bending
# ---------------------------------------------------------------------------------------------

def _crossing_times(t: np.ndarray, u: np.ndarray) -> np.ndarray:
    sgn = np.sign(u)
    idx = np.nonzero(sgn[:-1] * sgn[1:] < 0)[0]
    return t[idx] - u[idx] * (t[idx + 1] - t[idx]) / (u[idx + 1] - u[idx])


def bar_period(cells: int = 20, ppc_axis: int = 2, cfl: float = 0.4, transfer: str = "apic",
               periods: float = 2.0, fixed_dt: float = 0.0) -> tuple[float, float, MPMSolver]:
    """Free-free elastic bar (L = 1 m, 0.1 m square, ν = 0, E = 1e5 Pa, ρ = 1000 kg/m³: c = 10 m/s)
    started in its first longitudinal mode v = v0 cos(πx/L). Returns (measured period, expected
    2L/c, solver)."""
    L, h, E, rho = 1.0, 0.1, 1e5, 1000.0
    dx = L / cells
    h = max(h, 2 * dx)
    x, vol = lattice((0.0, 0.0, 0.0), (L, h, h), dx / ppc_axis)
    v0 = 0.02
    v = np.zeros_like(x)
    v[:, 0] = v0 * np.cos(math.pi * x[:, 0] / L)
    dom = box_domain((-0.3, -0.3, -0.3), (L + 0.3, h + 0.3, h + 0.3), dx)
    s = _solver(x, vol, _elastic(E, nu=0.0, density=rho), dom, v0=v, gravity=(0.0, 0.0, 0.0), cfl=cfl,
                transfer=transfer)
    expected = 2 * L / math.sqrt(E / rho)
    end = x[:, 0] < x[:, 0].min() + 0.5 * dx
    times = np.linspace(0.0, periods * expected, int(60 * periods) + 1)[1:]
    max_dt = fixed_dt if fixed_dt else math.inf
    if fixed_dt:
        s.stable_dt = lambda: math.inf  # the fixed step stands in for the CFL rule (reference configs)
    u = run_sampled(s, times, lambda s: float(s.positions()[end, 0].mean() - s.positions()[:, 0].mean()
                                              - (x[end, 0].mean() - x[:, 0].mean())), max_dt=max_dt)
    cross = _crossing_times(times, np.asarray(u))
    if len(cross) < 2:
        return math.nan, expected, s
    k = np.arange(len(cross))
    half = np.polyfit(k, cross, 1)[0]
    return 2 * half, expected, s


@timed
def bar_vibration(cells: int = 20) -> CaseResult:
    measured, expected, s = bar_period(cells)
    return CaseResult("elastic bar, longitudinal period", f"period (s), {cells} cells along the bar", measured,
                      expected, measured / expected - 1, 0.03,
                      "MPM's wave dispersion at 20 cells per length (measured order ~2 under refinement, "
                      "see convergence)", details={"substeps": s.substeps, "cells": cells})


@timed
def bar_convergence(cells=(10, 20, 40)) -> CaseResult:
    """Observed order of the bar period error under grid refinement."""
    errs = []
    for c in cells:
        measured, expected, _ = bar_period(c)
        errs.append(abs(measured / expected - 1))
    order = -np.polyfit(np.log(cells), np.log(errs), 1)[0]
    return CaseResult("convergence under grid refinement", "observed order of the bar-period error",
                      float(order), 2.0, float(order - 2.0), 0.8, "quadratic B-splines are second-order "
                      "accurate for smooth waves; the order is fitted over " + ", ".join(map(str, cells)) + " cells",
                      absolute=True, details={"cells": list(cells), "errors": errs})


@timed
def cantilever(cells_thick: int = 4, slenderness: float = 10.0) -> CaseResult:
    """A clamped beam sagging under its own weight (small load): tip deflection q L⁴ / (8 E I).
    Mass-proportional damping settles it to the static answer (damping does not change statics)."""
    h = 0.05
    dx = h / cells_thick
    L = slenderness * h
    rho, E = 1000.0, 0.0
    # E for a 1 % tip deflection: δ = 3 ρ g L⁴ / (2 E h²)
    E = 3 * rho * G * L**4 / (2 * 0.01 * L * h**2)
    clamp = 3 * dx
    x, vol = lattice((-clamp, 0.0, 0.0), (L, h, h), dx / 2)
    held = x[:, 0] < 0.0
    omega1 = 1.875**2 * math.sqrt(E * h**2 / 12 / rho) / L**2
    mat = _elastic(E, nu=0.0, density=rho, damping=1.2 * omega1)
    dom = box_domain((-clamp - 0.1, -0.1 - 0.05 * L, -0.1), (L + 0.1, h + 0.1, h + 0.1), dx)
    s = MPMSolver(x, vol, np.zeros(len(x), np.int64), [mat], dom, anchored=held)
    s.set_anchors(held, np.zeros_like(x))
    # The clamp is where the held material ends, x = 0: the anchor puts it on that edge between the grid
    # nodes (kernels.anchor_update, issue 22; before, every node their stencils touched was held, 1.5 dx
    # past them, and the free length was measured from that last node).
    clamp_x = 0.0
    L_free = float(x[:, 0].max() + dx / 4 - clamp_x)
    tip = x[:, 0] > x[:, 0].max() - 0.5 * dx
    t_settle = 8.0 / omega1
    (y_tip,) = run_sampled(s, [t_settle], lambda s: float(s.positions()[tip, 1].mean() - x[tip, 1].mean()))
    Ieff = h**4 / 12
    expected = rho * h * h * G * L_free**4 / (8 * E * Ieff)
    measured = -y_tip
    return CaseResult("cantilever under its own weight", f"tip deflection (m), L/h = {slenderness:g}, "
                      f"{cells_thick} cells thick", measured, expected, measured / expected - 1, 0.10,
                      "Euler–Bernoulli omits shear (+3(h/L)²·E/G… ≈ 1–2 % at L/h = 10); 4 cells across "
                      "the thickness resolve bending to a few %", details={"substeps": s.substeps,
                                                                            "free_length": L_free, "E": E})


# ---------------------------------------------------------------------------------------------
# Contact
# ---------------------------------------------------------------------------------------------

@timed
def friction_stop(mu: float = 0.3, v0: float = 1.0) -> CaseResult:
    """A block slides on Coulomb-friction ground from v0: it stops after v0² / (2 μ g)."""
    x, vol = lattice((0.0, 0.0, -0.05), (0.1, 0.05, 0.05), 0.00625)
    ground = Ground(0.0, "friction", mu)
    d = v0**2 / (2 * mu * G)
    dom = box_domain((-0.1, 0.0, -0.15), (d + 0.4, 0.3, 0.15), 0.0125, ground=ground)
    v = np.tile([v0, 0.0, 0.0], (len(x), 1))
    s = _solver(x, vol, _elastic(2e5), dom, v0=v, ground=ground)
    x0 = momentum(s)[2][0]
    t_stop = v0 / (mu * G)
    (com,) = run_sampled(s, [1.5 * t_stop], lambda s: momentum(s)[2], max_dt=FRAME_DT / MIN_SUBSTEPS)
    measured = float(com[0] - x0)
    return CaseResult("Coulomb friction stopping distance", f"distance (m), μ = {mu:g}, v0 = {v0:g} m/s",
                      measured, d, measured / d - 1, 0.05, "grid friction acts on the bottom nodes; the block "
                      "rocks slightly as it decelerates", details={"substeps": s.substeps})


def slope_run(model: str, degrees: float, mu: float = 0.5, t_end: float = 1.0, E: float = 2e5,
              dx: float = 0.01, transfer: str = "apic", size=(0.1, 0.05, 0.1),
              v0: float = 0.0) -> tuple[np.ndarray, np.ndarray, float]:
    """A block of ``size`` (x, y = height, z; default 0.1 x 0.05 x 0.1 m; rigid, or jelly of Young's
    modulus E) released at rest (or at ``v0`` downhill) on a Coulomb ground of friction μ, the slope
    made by tilting gravity by ``degrees`` about z (downhill is +x). Returns (times, the centre of
    mass's travel along the slope, dx)."""
    w, h, d = size
    x, vol = lattice((-w / 2, 0.0, -d / 2), (w / 2, h, d / 2), dx / 2)
    ground = Ground(0.0, "friction", mu)
    th = math.radians(degrees)
    reach = 0.5 * G * max(math.sin(th) - mu * math.cos(th), 0.0) * t_end ** 2 + v0 * t_end + 0.15
    dom = box_domain((-w / 2 - 0.1, 0.0, -d / 2 - 0.07), (w / 2 + 0.05 + reach, h + 0.1, d / 2 + 0.07), dx,
                     ground=ground)
    mat = material_preset("rigid") if model == "rigid" else _elastic(E)
    s = _solver(x, vol, mat, dom, ground=ground, gravity=(G * math.sin(th), -G * math.cos(th), 0.0),
                body=np.zeros(len(x), np.int64) if model == "rigid" else None, transfer=transfer,
                v0=np.tile([v0, 0.0, 0.0], (len(x), 1)) if v0 else None)
    m = s.mass_np.astype(np.float64)
    x0 = float((x[:, 0] * m).sum() / m.sum())
    times = np.linspace(0.0, t_end, 11)[1:]
    com = run_sampled(s, list(times), lambda s: float((s.positions()[:, 0].astype(np.float64) * m).sum() / m.sum()),
                      max_dt=FRAME_DT / MIN_SUBSTEPS)
    return times, np.asarray(com) - x0, dx


TALL_BLOCK = (0.14, 0.1, 0.1)  # 10 cells tall at dx = 1 cm: it crept before the ground friction's memory


@timed
def slope_friction(mu: float = 0.5) -> list[CaseResult]:
    """Blocks on a Coulomb slope (μ = 0.5, holding up to tan θ = μ, 26.6°): at 0.9 μ (24.2°) a rigid
    and a stiff jelly block (E = 2e5 Pa; 5 and 10 cells tall) must hold (travel under half a cell in
    1 s); at 30° and 40° they slide with a = g (sin θ − μ cos θ)."""
    out = []
    hold = math.degrees(math.atan(0.9 * mu))
    for model, size in (("rigid", None), ("jelly", None), ("jelly", TALL_BLOCK)):
        t, travel, dx = slope_run(model, hold, mu, **({"size": size} if size else {}))
        what = model + (", E = 2e5 Pa" if model == "jelly" else "")
        if size:
            what += f", {round(size[1] / dx)} cells tall"
        out.append(CaseResult(f"block on a slope at 0.9 μ ({what})",
                              f"travel along the slope in {t[-1]:g} s, in cells (θ = {hold:.1f}°, μ = {mu:g})",
                              float(travel[-1] / dx), 0.0, float(travel[-1] / dx), 0.5,
                              "static friction holds any body up to tan θ = μ; half a cell is the issue's bound "
                              "(what the grid's contact layer may settle by)", absolute=True,
                              details={"travel_m": [float(v) for v in travel]}))
    for degrees in (30.0, 40.0):
        th = math.radians(degrees)
        expected = G * (math.sin(th) - mu * math.cos(th))
        for model in ("rigid", "jelly"):
            t, travel, _ = slope_run(model, degrees, mu, t_end=0.5)
            sel = t >= 0.1
            accel = 2.0 * float(np.polyfit(t[sel], travel[sel], 2)[0])
            out.append(CaseResult(f"block sliding down a {degrees:g}° slope ({model})",
                                  f"acceleration along the slope (m/s²), μ = {mu:g}", accel, expected,
                                  accel / expected - 1, 0.05,
                                  "Coulomb's kinetic friction μ N; 5 % covers the start (the body settles onto the "
                                  "ground in the first substeps) and, for the jelly, its rocking",
                                  details={"travel_m": [float(v) for v in travel]}))
    return out


@timed
def bouncing_ball(drop: float = 0.2) -> CaseResult:
    """An elastic ball dropped on slip ground: the mechanical energy (kinetic + gravitational; the
    elastic part is not counted and is ≥ 0) never exceeds its start, and the rebound height is reported."""
    r = 0.05
    x, vol = ball((0.0, drop + r, 0.0), r, r / 8)
    ground = Ground(0.0, "slip")
    dom = box_domain((-0.2, 0.0, -0.2), (0.2, drop + 2 * r + 0.1, 0.2), r / 4, ground=ground)
    s = _solver(x, vol, _elastic(2e5, nu=0.3, model="neo_hookean"), dom, ground=ground)
    m = s.mass_np.astype(np.float64)
    times = np.linspace(0.0, 2.2 * math.sqrt(2 * drop / G), 200)[1:]

    def obs(s):
        kin, pot = s.energy()
        return kin + pot, float((s.positions()[:, 1].astype(np.float64) * m).sum() / m.sum())

    rec = run_sampled(s, times, obs)
    kin0, pot0 = 0.0, float(-(m * (x @ np.array([0.0, -G, 0.0]))).sum())
    e0 = kin0 + pot0
    energy = np.array([e for e, _ in rec])
    height = np.array([h for _, h in rec]) - r
    # Rebound: the highest point after the first contact.
    first_low = int(np.argmin(height[: len(height) // 2 + 20]))
    rebound = float(height[first_low:].max())
    gain = float((energy.max() - e0) / (m.sum() * G * drop))
    return CaseResult("bouncing elastic ball", "energy gain, max(E_kin + E_grav) − E0, in units of m g h",
                      gain, 0.0, gain, 0.01, "an explicit scheme must not create energy; 1 % allows "
                      "float32 round-off", absolute=True,
                      details={"rebound_ratio": rebound / drop, "substeps": s.substeps})


def landing_run(gap: Optional[float], v_up: float = 0.0, drop: float = 0.03, dx: float = 0.0125,
                t_end: float = 0.5) -> tuple[float, float]:
    """A stiff elastic block (E = 2e6 Pa, 0.1 x 0.1 x 0.05 m = 8 cells tall, lattice of dx/2) on Coulomb
    ground (μ = 0.5): dropped from ``drop`` above it, or resting on it and thrown straight up at ``v_up``.
    MPMSolver's ``ground_gap`` = ``gap``. Returns, after ``t_end``, its underside's height above the plane
    (the lowest particle's centre less half a spacing) and its centre of mass's rise since the start, in
    cells."""
    bottom = 0.0 if v_up else drop
    x, vol = lattice((-0.05, bottom, -0.025), (0.05, bottom + 0.1, 0.025), dx / 2)
    ground = Ground(0.0, "friction", 0.5)
    dom = box_domain((-0.15, 0.0, -0.1), (0.15, 0.3, 0.1), dx, ground=ground)
    v = np.tile([0.0, v_up, 0.0], (len(x), 1)) if v_up else None
    s = _solver(x, vol, _elastic(2e6), dom, ground=ground, v0=v, ground_gap=gap)
    m = s.mass_np.astype(np.float64)
    (y,) = run_sampled(s, [t_end], lambda s: s.positions()[:, 1].astype(np.float64), max_dt=FRAME_DT / MIN_SUBSTEPS)
    underside = float(y.min()) - dx / 4
    rise = float((y * m).sum() / m.sum() - (x[:, 1] * m).sum() / m.sum())
    return underside / dx, rise / dx


@timed
def landing() -> list[CaseResult]:
    """A stiff block dropped on the ground rests on it, and one thrown up from it comes back down:
    not held up to a cell and a half above the plane, where the ground nodes' B-splines reach."""
    why = ("the ground acts on a column only where the material's underside is within 0.15 cells of the plane "
           "(or comes in faster than a fall through the nodes' reach); a quarter of a cell is what a viewer "
           "barely sees. Plain grid contact: {old:.2f} cells")
    drop_old, _ = landing_run(None)
    drop_new, _ = landing_run(GROUND_GAP)
    _, up_old = landing_run(None, v_up=0.5)
    _, up_new = landing_run(GROUND_GAP, v_up=0.5)
    return [
        CaseResult("stiff block dropped 3 cm (E = 2e6 Pa)", "underside above the ground after 0.5 s (cells)",
                   drop_new, 0.0, drop_new, 0.25, why.format(old=drop_old), absolute=True),
        CaseResult("stiff block thrown up from the ground at 0.5 m/s", "centre of mass above its start after 0.5 s "
                   "(cells)", up_new, 0.0, up_new, 0.25, why.format(old=up_old), absolute=True),
    ]


def head_on(E: float, speed: float = 0.8, cells: int = 8, contact: str = "friction", transfer: str = "apic",
            t_end: float = 0.2) -> tuple[float, float, int]:
    """Two equal elastic balls (radius 5 cm, ``cells`` grid cells across, 8 particles a cell) meet
    head-on at a closing speed ``speed`` without gravity, each object on its own velocity field
    (``contact``: ObjectContact's; "shared" = one field for both). Returns the coefficient of
    restitution (the centres of mass's separation speed after over the approach speed), the total
    momentum at the end relative to one ball's, and the substeps."""
    r = 0.05
    dx = 2 * r / cells
    x1, v1 = ball((-r - dx, 0.0, 0.0), r, dx / 2)
    x2, v2 = ball((r + dx, 0.0, 0.0), r, dx / 2)
    x, vol = np.concatenate([x1, x2]), np.concatenate([v1, v2])
    obj = np.repeat([0, 1], [len(x1), len(x2)])
    v = np.zeros_like(x)
    v[obj == 0, 0], v[obj == 1, 0] = 0.5 * speed, -0.5 * speed
    dom = box_domain((-4 * r, -2 * r, -2 * r), (4 * r, 2 * r, 2 * r), dx)
    mat = _elastic(E)
    s = MPMSolver(x, vol, obj, [mat, mat], dom, gravity=(0.0, 0.0, 0.0), v0=v, transfer=transfer,
                  object_contact=ObjectContact(contact))
    m = s.mass_np.astype(np.float64)
    s.set_limits(max_dt=FRAME_DT / MIN_SUBSTEPS)
    s.advance(t_end)
    vel = s.velocities().astype(np.float64)
    vc = [float((m[obj == k] * vel[obj == k, 0]).sum() / m[obj == k].sum()) for k in (0, 1)]
    p = float((m[:, None] * vel).sum(0)[0]) / (m[obj == 0].sum() * 0.5 * speed)
    return (vc[1] - vc[0]) / speed, p, s.substeps


def ground_bounce(E: float, speed: float = 0.8, cells: int = 8, transfer: str = "apic",
                  t_end: float = 0.12, contact: str = "slip", mu: float = 0.5) -> float:
    """An elastic ball (radius 5 cm, ``cells`` across) hits the ground (``contact``: slip, or Coulomb
    friction μ) head-on at ``speed`` without gravity; returns the coefficient of restitution (its
    centre of mass's rebound speed over ``speed``)."""
    r = 0.05
    dx = 2 * r / cells
    ground = Ground(0.0, contact, mu)
    x, vol = ball((0.0, r + dx, 0.0), r, dx / 2)
    dom = box_domain((-2 * r, 0.0, -2 * r), (2 * r, 6 * r, 2 * r), dx, ground=ground)
    s = _solver(x, vol, _elastic(E), dom, ground=ground, gravity=(0.0, 0.0, 0.0),
                v0=np.tile([0.0, -speed, 0.0], (len(x), 1)), transfer=transfer)
    s.set_limits(max_dt=FRAME_DT / MIN_SUBSTEPS)
    s.advance(t_end)
    m = s.mass_np.astype(np.float64)
    return float((m * s.velocities()[:, 1].astype(np.float64)).sum() / m.sum()) / speed


@timed
def restitution(speed: float = 0.8) -> list[CaseResult]:
    """Elastic balls without damping bounce back almost fully: two equal balls meeting head-on at
    0.8 m/s, each on its own velocity field with Coulomb contact between them (Bardenhagen et al.
    2000), and a ball on slip ground; jelly (E = 2e4 Pa) and a stiff jelly (E = 2e5 Pa), at 10 cells
    across a ball (what the CPU's default 24 cells across a two-ball scene gives)."""
    out = []
    why = ("an elastic body without damping returns its energy (e → 1 as the grid refines); the issue's bound "
           "is e ≥ 0.85 (a rubber ball: 0.8-0.9); the rest is the transfers' numerical dissipation")
    for E in (2e4, 2e5):
        e, p, n = head_on(E, speed, cells=10)
        out.append(CaseResult(f"two elastic balls head-on (E = {E:g} Pa)",
                              f"coefficient of restitution at {speed:g} m/s, 10 cells a ball", e, 1.0, e - 1.0,
                              0.15, why, absolute=True, details={"momentum_rel": p, "substeps": n}))
        e = ground_bounce(E, speed, cells=10)
        out.append(CaseResult(f"elastic ball on slip ground (E = {E:g} Pa)",
                              f"coefficient of restitution at {speed:g} m/s, 10 cells a ball", e, 1.0, e - 1.0,
                              0.15, why, absolute=True))
    # On Coulomb ground an elastic solid's contact layer transfers without APIC's affine part (what
    # holds it on a slope, kernels.p2g); that layer's PIC dissipation costs bounce (measured 0.87,
    # 0.96 before): reported against the same bound.
    e = ground_bounce(2e5, speed, cells=10, contact="friction")
    out.append(CaseResult("elastic ball on Coulomb ground (E = 2e+05 Pa, μ = 0.5)",
                          f"coefficient of restitution at {speed:g} m/s, 10 cells a ball", e, 1.0, e - 1.0, 0.15,
                          why + "; on Coulomb ground the contact layer moves by PIC", absolute=True))
    return out


def block_over_block(contact: str, mu: float, v0: float = 0.5, t_end: float = 0.25,
                     dx: float = 0.0125) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A jelly block (E = 2e5 Pa, 0.1 x 0.03 x 0.05 m) launched at v0 along x over a wider jelly block
    (0.3 x 0.04 x 0.07 m) resting on sticky ground, each on its own velocity field (ObjectContact
    ``contact``, μ), 24 cells across the scene (dx), particles on a lattice of dx/2. Returns the sample
    times, the top block's travel along x and the rise of its centre of mass."""
    xb, vb = lattice((-0.15, 0.0, -0.035), (0.15, 0.04, 0.035), dx / 2)
    xt, vt = lattice((-0.12, 0.04, -0.025), (-0.02, 0.07, 0.025), dx / 2)
    x, vol = np.concatenate([xb, xt]), np.concatenate([vb, vt])
    obj = np.repeat([0, 1], [len(xb), len(xt)])
    v = np.zeros_like(x)
    v[obj == 1, 0] = v0
    ground = Ground(0.0, "sticky")
    dom = box_domain((-0.25, 0.0, -0.1), (0.25 + v0 * t_end, 0.15, 0.1), dx, ground=ground)
    mat = _elastic(2e5)
    s = MPMSolver(x, vol, obj, [mat, mat], dom, v0=v, ground=ground, object_contact=ObjectContact(contact, mu))
    m = s.mass_np.astype(np.float64)
    top = obj == 1
    c0 = (x[top] * m[top, None]).sum(0) / m[top].sum()
    times = np.linspace(0.0, t_end, 26)[1:]
    com = run_sampled(s, list(times), lambda s: (s.positions()[top].astype(np.float64) * m[top, None]).sum(0)
                      / m[top].sum(), max_dt=FRAME_DT / MIN_SUBSTEPS)
    com = np.asarray(com)
    return times, com[:, 0] - c0[0], com[:, 1] - c0[1]


@timed
def object_sliding(v0: float = 0.5) -> list[CaseResult]:
    """A block sliding over another object (both jelly, each on its own velocity field): with Coulomb
    contact it stops after v0² / (2 μ g) (μ = 0.5 and 0.25); with slip contact it keeps its speed."""
    out = []
    why = ("Coulomb friction between the objects' velocity fields, acting only where their material fills a "
           "node (the fill check); 10 % covers the block pitching onto its leading edge, where the contact "
           "normal tilts (measured −2 … −12 % through simulate() over five offsets of the interface in a cell)")
    for mu in (0.5, 0.25):
        d = v0 ** 2 / (2 * mu * G)
        t, travel, rise = block_over_block("friction", mu, v0, t_end=max(0.25, 2.0 * v0 / (mu * G)))
        out.append(CaseResult(f"block sliding over a block (jelly, μ = {mu:g})",
                              f"stopping distance (m) from {v0:g} m/s, 8 cells along the block", float(travel[-1]),
                              d, float(travel[-1]) / d - 1, 0.10, why,
                              details={"rise_m": float(rise[-1]), "travel_m": [float(a) for a in travel]}))
    t, travel, rise = block_over_block("slip", 0.0, v0, t_end=0.25)
    out.append(CaseResult("block sliding over a block (jelly, slip contact)",
                          f"distance in {t[-1]:g} s (m) at {v0:g} m/s", float(travel[-1]), v0 * float(t[-1]),
                          float(travel[-1]) / (v0 * float(t[-1])) - 1, 0.05,
                          "nothing slows a block on frictionless contact; what is taken is the normal's tilt at "
                          "the corners of its leading face",
                          details={"rise_m": float(rise[-1])}))
    return out


# ---------------------------------------------------------------------------------------------
# Viscosity: the decay of a Taylor-Green vortex
# ---------------------------------------------------------------------------------------------

TG_SIDE = 0.1  # m: the vortex fills a square box of this side (the flow in issue 37's audit)


def maxwell_decay_rate(viscosity: float, shear_modulus: float, density: float, k2: float) -> float:
    """Decay rate (1/s) of the slow mode of a linear Maxwell liquid (relaxation time λ = η/μ) in a
    divergence-free shear mode with ∇²φ = −k2 φ: with velocity a φ and elastic strain b sym∇φ,
    ρ ȧ = −μ k2 b and ḃ = a − b/λ, so s² + s/λ + μ k2/ρ = 0; the slow root tends to the Newtonian
    rate η k2 / ρ as λ → 0. (Shear modulus ∞: exactly the Newtonian rate.)"""
    if not math.isfinite(shear_modulus):
        return viscosity * k2 / density
    inv_lam = shear_modulus / viscosity
    w2 = shear_modulus * k2 / density
    disc = inv_lam * inv_lam - 4.0 * w2
    if disc < 0:  # under-damped: the amplitude's envelope decays at 1/(2λ)
        return 0.5 * inv_lam
    return 0.5 * (inv_lam - math.sqrt(disc))


def taylor_green_rate(mat: Material, cells: int, speed: float = 0.01, t_end: float = 0.12,
                      t_fit: float = 0.02) -> tuple[float, MPMSolver]:
    """The decay rate (1/s) of a Taylor-Green vortex u = U (sin kx cos ky, −cos kx sin ky, 0),
    k = π/L, filling a box of side L = TG_SIDE with slip walls (the mode has no normal velocity and
    no shear stress there, so the walls are exact), two cells thick in z, no gravity, ``cells``
    cells across. The amplitude is the mode's projection a = Σ m v·φ / Σ m φ·φ at the particles'
    current places; the rate is the slope of log a fitted from ``t_fit`` (past the Maxwell liquid's
    fast mode) to ``t_end``. U = 1 cm/s keeps the flow linear (Reynolds number ρUL/η ~ 1e-4)."""
    L = TG_SIDE
    dx = L / cells
    h = 2 * dx
    x, vol = lattice((0.0, 0.0, 0.0), (L, L, h), dx / 2)
    k = math.pi / L

    def mode(xs):
        sx, cx = np.sin(k * xs[:, 0]), np.cos(k * xs[:, 0])
        sy, cy = np.sin(k * xs[:, 1]), np.cos(k * xs[:, 1])
        phi = np.stack([sx * cy, -cx * sy, np.zeros(len(xs))], 1)
        grad = np.zeros((len(xs), 3, 3))  # ∂φ_i/∂x_j: APIC's C starts as the flow's gradient
        grad[:, 0, 0] = k * cx * cy
        grad[:, 0, 1] = -k * sx * sy
        grad[:, 1, 0] = k * sx * sy
        grad[:, 1, 1] = -k * cx * cy
        return phi, grad

    phi, grad = mode(x)
    dom = box_domain((0.0, 0.0, 0.0), (L, L, h), dx)
    s = _solver(x, vol, mat, dom, v0=speed * phi, C0=speed * grad, gravity=(0.0, 0.0, 0.0))
    m = s.mass_np.astype(np.float64)

    def amplitude(s):
        p, _ = mode(s.positions().astype(np.float64))
        v = s.velocities().astype(np.float64)
        return float((m * (v * p).sum(1)).sum() / (m * (p * p).sum(1)).sum())

    times = np.linspace(t_fit, t_end, 13)
    amps = np.asarray(run_sampled(s, list(times), amplitude))
    rate = -float(np.polyfit(times, np.log(amps), 1)[0])
    return rate, s


def _viscous_materials() -> list[tuple[str, Material, float]]:
    """(label, material, expected decay rate) of the viscosity cases: honey (the viscoplastic
    model, its yield stress lowered to 1e-3 Pa so that it flows as the Maxwell liquid it is above
    yield) and a Newtonian liquid of the fluid model with the same η and ρ (a bulk modulus
    giving the same 5 m/s sound speed)."""
    k2 = 2.0 * (math.pi / TG_SIDE) ** 2
    honey = material_preset("honey", yield_stress=1e-3)
    fluid = Material(name="viscous liquid", model="fluid", E=1.0, nu=0.0, density=honey.density,
                     bulk_modulus=5000.0, gamma=7.0, viscosity=honey.viscosity)
    return [("viscoplastic (honey, η = 10 Pa·s)", honey,
             maxwell_decay_rate(honey.viscosity, honey.mu, honey.density, k2)),
            ("fluid (η = 10 Pa·s)", fluid, maxwell_decay_rate(fluid.viscosity, math.inf, fluid.density, k2))]


def extrapolate(cells, values) -> tuple[float, float]:
    """Richardson extrapolation of ``values`` measured at ``cells`` (each grid twice the last): from
    the last three with their observed order, from two assuming second order. Returns (value, order)."""
    if len(values) >= 3:
        a, b, c = values[-3:]
        ratio = (a - b) / (b - c) if b != c else math.inf
        if ratio > 1.0 and math.isfinite(ratio):
            p = math.log(ratio, cells[-1] / cells[-2])
            return c + (c - b) / ((cells[-1] / cells[-2]) ** p - 1.0), p
    b, c = values[-2:]
    r = cells[-1] / cells[-2]
    return c + (c - b) / (r * r - 1.0), 2.0


@timed
def viscosity_taylor_green(cells=(16, 32, 64), materials=None) -> list[CaseResult]:
    """The viscosity a flow shows, against the one the material states: a Taylor-Green vortex's
    decay rate at grids of doubling resolution, for the viscoplastic model (honey: a Maxwell liquid,
    relaxation time η/μ, whose slow mode decays at the root of s² + s μ/η + μ k²/ρ = 0) and the fluid
    model (Newtonian: η k²/ρ), k² = 2 (π/L)². The rate converges from above (the grid's smoothing
    adds dissipation); it is judged extrapolated to zero cell size (Richardson, observed order) and
    the finest grid's own error is in the details."""
    out = []
    for label, mat, expected in materials or _viscous_materials():
        rates = [taylor_green_rate(mat, c)[0] for c in cells]
        errs = [r / expected - 1 for r in rates]
        value, order = extrapolate(cells, rates)
        three = len(cells) >= 3
        out.append(CaseResult(
            f"Taylor-Green vortex decay, {label}",
            f"decay rate (1/s), extrapolated from {', '.join(str(c) for c in cells)} cells across",
            value, expected, value / expected - 1, 0.03 if three else 0.04,
            "the extrapolation leaves the error of its assumed order: with the observed order (~1.6-1.8, "
            "three grids) well under 1 %, with second order assumed (two grids) ~2 %; 3 % (4 %) leaves room. "
            "At 16/32/64 cells the raw rate is ~21 / 7 / 2 % high; before issue 37 honey's was half "
            "(it flowed with η/2)",
            details={"cells": list(cells), "rates": rates, "errors": errs, "order": order,
                     "newtonian_rate": mat.viscosity * 2.0 * (math.pi / TG_SIDE) ** 2 / mat.density}))
    return out


# ---------------------------------------------------------------------------------------------
# Granular flow
# ---------------------------------------------------------------------------------------------

def lube_runout(a: float, geometry: str = "plane") -> float:
    """Run-out of a granular column of aspect ratio a = H0/L0, from the experiments' scaling laws.

    plane (a 2-D column against a wall, run-out (L∞ − L0)/L0): 1.2 a for a < 2.3, 1.9 a^(2/3) above
    (Lube et al. 2005, Phys. Rev. E 72, 041301; Lajeunesse et al. 2005 find the same).
    axisymmetric (a cylinder, (R∞ − R0)/R0): 1.24 a for a < 1.7, 1.6 a^(1/2) above (Lube et al.
    2004, J. Fluid Mech. 508; Lajeunesse et al. 2004, Phys. Fluids 16, 2371).
    """
    if geometry == "plane":
        return 1.2 * a if a < 2.3 else 1.9 * a ** (2.0 / 3.0)
    return 1.24 * a if a < 1.7 else 1.6 * a ** 0.5


@timed
def column_collapse(aspect: float = 1.0, cells: int = 16, geometry: str = "plane", base_friction: float = 0.5,
                    friction_angle: float = 32.0, t_end: float = 0.0,
                    yield_surface: str = "plane_strain") -> CaseResult:
    """A dry-sand column released on rough ground (Coulomb μ = ``base_friction``); its run-out is
    compared with the experiments' scaling law. ``plane``: width L0 against a slip wall, in a narrow
    slip-walled channel (plane strain). ``axisymmetric``: a cylinder of radius L0 on open ground.
    ``yield_surface``: the sand's Drucker–Prager cone, matched to Mohr–Coulomb in plane strain (the
    suite's choice: the flow is plane strain, and the axisymmetric slump spreads with one principal
    strain rate near zero too) or in triaxial compression (the sand preset's default)."""
    L0 = 0.1 if geometry == "plane" else 0.05
    H0 = aspect * L0
    dx = L0 / cells
    runout = lube_runout(aspect, geometry) * L0
    ground = Ground(0.0, "friction", base_friction)
    if geometry == "plane":
        width = 4 * dx
        x, vol = lattice((0.0, 0.0, 0.0), (L0, H0, width), dx / 2)
        dom = box_domain((0.0, 0.0, 0.0), (L0 + 2.0 * runout + 0.1, H0 + 0.05, width), dx, ground=ground)
    else:
        x, vol = lattice((-L0, 0.0, -L0), (L0, H0, L0), dx / 2)
        keep = np.hypot(x[:, 0], x[:, 2]) <= L0
        x, vol = x[keep], vol[keep]
        reach = L0 + 1.6 * runout + 0.05
        dom = box_domain((-reach, 0.0, -reach), (reach, H0 + 0.05, reach), dx, ground=ground)
    s = _solver(x, vol, material_preset("sand", friction_angle=friction_angle, yield_surface=yield_surface), dom,
                ground=ground)
    t_end = t_end or 3.5 * math.sqrt(H0 / G) + 0.2
    run_sampled(s, [t_end], lambda s: None, max_dt=FRAME_DT / MIN_SUBSTEPS)
    xs = s.positions().astype(np.float64)
    # The front: the far edge of the last dx-wide slice (plane) or ring (axisymmetric) that still
    # holds half a particle layer; a stray grain ahead of the deposit does not count.
    layer_density = 1.0 / (dx / 2) ** 2  # particles per m² of one layer
    r = xs[:, 0] if geometry == "plane" else np.hypot(xs[:, 0], xs[:, 2])
    edges = np.arange(0.0, float(r.max()) + 2 * dx, dx)
    counts, _ = np.histogram(r, bins=edges)
    area = (np.full(len(counts), dx * width) if geometry == "plane"
            else math.pi * (edges[1:] ** 2 - edges[:-1] ** 2))
    full = np.nonzero(counts / area >= 0.5 * layer_density)[0]
    front = float(edges[full[-1] + 1]) if len(full) else math.nan
    measured = (front - L0) / L0
    expected = runout / L0
    cone = {"plane_strain": "plane-strain cone", "triaxial": "triaxial cone"}[yield_surface]
    return CaseResult(f"granular collapse ({geometry}, {cone}), a = {aspect:g}", "run-out (L∞ − L0)/L0", measured,
                      expected, measured / expected - 1, 0.35,
                      "experiments scatter ±15 % about the law; Drucker–Prager without a rate-dependent μ(I) is "
                      "reported within ~20–30 %; the base friction μ = 0.5 stands for the experiments' rough bed",
                      details={"substeps": s.substeps, "cells": cells, "base_friction": base_friction,
                               "friction_angle": friction_angle, "yield_surface": yield_surface})


CaseFn = Callable[[], "CaseResult | list[CaseResult]"]


def all_cases(quick: bool = False) -> list[tuple[str, CaseFn]]:
    """(name, callable) for every case; ``quick`` keeps the ones that take seconds on a CPU."""
    cases: list[tuple[str, CaseFn]] = [
        ("free_fall", free_fall),
        ("projectile", projectile),
        ("momentum", momentum_conservation),
        ("torque", torque_spin_up),
        ("bar", bar_vibration),
        ("friction", friction_stop),
        ("ball", bouncing_ball),
        ("landing", landing),
        ("rigid_rotation", rigid_free_rotation),
        ("tennis_racket", tennis_racket),
        ("symmetric_top", symmetric_top),
        ("rigid_fall", rigid_free_fall),
        ("elastic_tumbling", elastic_tumbling),
    ]
    if not quick:
        cases += [
            ("convergence", bar_convergence),
            ("cantilever", cantilever),
            ("viscosity", viscosity_taylor_green),
            ("slope", slope_friction),
            ("restitution", restitution),
            ("object_sliding", object_sliding),
            ("collapse_0.5", lambda: column_collapse(0.5)),
            ("collapse_1", lambda: column_collapse(1.0)),
            ("collapse_3", lambda: column_collapse(3.0)),
            ("collapse_axi_1", lambda: column_collapse(1.0, cells=10, geometry="axisymmetric")),
        ]
    return cases


def run_cases(names=None, quick: bool = False, progress=None) -> list[CaseResult]:
    results: list[CaseResult] = []
    chosen = [(n, f) for n, f in all_cases(quick) if names is None or n in names]
    for i, (name, fn) in enumerate(chosen):
        if progress:
            progress(i, len(chosen), name)
        out = fn()
        results.extend(out if isinstance(out, list) else [out])
    return results
