"""Stability stress tests: extreme materials, loads, shapes, run lengths and steps.

Every case goes through ``simulate`` exactly as a user's run does, and must end one of two ways:

* **completed** — every particle finite and inside the domain, no particle's deformation gradient
  inverted or collapsed (det F > 0 in every frame), the mean elastic volume ratio det F within
  [1/2, 2] at the end (a body crushed flat has not survived, whatever its energy), and the
  mechanical energy bounded:
  E_kin + E_grav never exceeds its start plus the work the external forces did (the elastic
  energy is not counted and is never negative, so this is a necessary condition), within 5 % of
  the energy scale of the case;
* **refused** — an ``InputError`` before the first substep, whose message names the cause and the fix.

Anything else (a ``SimulationError`` mid-run, another exception, an energy blow-up) is a failure.
``physmotion stress`` runs the matrix and writes docs/stability.md; the tests run the quick subset.
"""

from __future__ import annotations

import itertools
import time
import traceback
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
import torch

from ..errors import InputError, PhysMotionError
from ..types.material import material_preset
from ..sim.simulate import simulate
from ..types.conditions import Conditions, Force, Gravity, Ground, InitialVelocity, Torque, Walls
from ..types.gaussians import Gaussians
from ..types.material import Material
from ..types.settings import SimSettings

ENERGY_SLACK = 0.05
MAX_VOLUME_CHANGE = 2.0  # the elastic volume ratio det F, averaged at the end, must stay within [1/2, 2]


def gaussian_box(lo, hi, counts, sigma: Optional[float] = None) -> Gaussians:
    """Gaussians on a counts[0]×counts[1]×counts[2] lattice filling the box lo..hi (metres)."""
    axes = [torch.linspace(float(a), float(b), int(k)) for a, b, k in zip(lo, hi, counts)]
    p = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    steps = [(b - a) / (k - 1) for a, b, k in zip(lo, hi, counts) if k > 1]
    s = sigma if sigma is not None else 0.5 * min(steps)
    gen = torch.Generator().manual_seed(0)
    return Gaussians.from_rgb(p, torch.rand(len(p), 3, generator=gen), torch.full((len(p), 3), s),
                              torch.full((len(p),), 0.9))


@dataclass
class StressCase:
    name: str
    group: str
    build: Callable[[], tuple]  # → (gaussians, materials, conditions, settings)
    quick: bool = False


@dataclass
class StressOutcome:
    name: str
    group: str
    status: str  # completed / refused / failed
    reason: str = ""
    seconds: float = 0.0
    details: dict = field(default_factory=dict)


def _check_completed(res) -> tuple[bool, str, dict]:
    x = res.x.numpy()
    if not np.all(np.isfinite(x)):
        return False, "non-finite positions", {}
    J = np.linalg.det(res.F.numpy().astype(np.float64))  # (T, P): each particle's volume ratio
    if J.size and not np.all(np.isfinite(J)):
        return False, "non-finite deformation gradients", {}
    if J.size and J.min() <= 0.0:
        t, p = np.unravel_index(int(np.argmin(J)), J.shape)
        return False, f"inverted or crushed material: det F = {J[t, p]:.2g} (particle {p}, frame {t})", {}
    mean_j = float(J[-1].mean()) if J.size else 1.0
    if not (1.0 / MAX_VOLUME_CHANGE <= mean_j <= MAX_VOLUME_CHANGE):
        return False, f"lost its volume: mean det F = {mean_j:.3g} at the end (elastic part)", {}
    e = res.stats["energy"]
    kin, pot, work = (np.asarray(e[k], float) for k in ("kinetic", "potential", "work"))
    mech = kin + pot - (kin[0] + pot[0]) - work
    height = float(x[0][:, 1].max() - x[0][:, 1].min())
    scale = kin[0] + res.stats["mass_kg"] * 9.81 * max(height, 1e-3) + float(np.abs(work).max())
    excess = float(mech[1:].max() if len(mech) > 1 else 0.0) / scale  # < 0: energy was dissipated
    details = {"substeps": res.stats["substeps"], "energy_excess": excess, "particles": res.stats["particles"]}
    if excess > ENERGY_SLACK:
        return False, f"energy grew by {excess:.1%} of its scale beyond the external work", details
    return True, f"{res.stats['substeps']} substeps, energy excess {excess:+.1%}", details


def run_case(case: StressCase) -> StressOutcome:
    t0 = time.perf_counter()
    try:
        g, mats, conds, settings = case.build()
    except InputError as exc:  # refused while the inputs are built (e.g. an invalid material)
        return StressOutcome(case.name, case.group, "refused", str(exc), time.perf_counter() - t0)
    try:
        res = simulate(g, mats, conds, settings, record_all=True)
    except InputError as exc:
        return StressOutcome(case.name, case.group, "refused", str(exc), time.perf_counter() - t0)
    except PhysMotionError as exc:
        return StressOutcome(case.name, case.group, "failed", f"{type(exc).__name__}: {exc}",
                             time.perf_counter() - t0)
    except Exception as exc:  # a crash is a failure, reported with where it happened
        tb = traceback.extract_tb(exc.__traceback__)[-1]
        return StressOutcome(case.name, case.group, "failed",
                             f"{type(exc).__name__}: {exc} ({tb.filename}:{tb.lineno})", time.perf_counter() - t0)
    ok, why, details = _check_completed(res)
    return StressOutcome(case.name, case.group, "completed" if ok else "failed", why, time.perf_counter() - t0,
                         details)


# ---------------------------------------------------------------------------------------------
# The matrix
# ---------------------------------------------------------------------------------------------

#: Frames of the force and torque cases (0.5 s at 24 fps): the checks read the end state, and a body a load
#: slams into the walls must have time to recover from the impact before it is judged (the jelly under
#: 1e3 N·m, at ~1e3 m/s, is at mean det F 0.45 two frames after the torque ends and 0.9 two frames later).
LOAD_FRAMES = 12


def _cube(size: float = 0.1, lift: float = 0.02, n: int = 6) -> Gaussians:
    h = size / 2
    return gaussian_box((-h, lift, -h), (h, lift + size, h), (n, n, n))


def _settings(**kw) -> SimSettings:
    base = dict(frames=3, fps=24.0, grid_res=6, particles_per_cell=1, domain_margin=0.5, device="cpu")
    base.update(kw)
    return SimSettings(**base)


def _ground() -> list:
    return [Ground(0.0, "slip")]


def cases() -> list[StressCase]:
    out: list[StressCase] = []
    quick_materials = {(1e3, 0.499, 1.0), (1e7, 0.45, 2e4), (1e11, 0.3, 1.0), (1e5, 0.0, 1000.0)}
    for E, nu, rho in itertools.product((1e3, 1e5, 1e7, 1e9, 1e11), (0.0, 0.3, 0.45, 0.499), (1.0, 1e3, 2e4)):
        def build(E=E, nu=nu, rho=rho):
            mat = Material(name="elastic", model="fixed_corotated", E=E, nu=nu, density=rho)
            return _cube(), mat, Conditions(_ground()), _settings()
        out.append(StressCase(f"E={E:.0e} ν={nu:g} ρ={rho:g}", "material", build,
                              quick=(E, nu, rho) in quick_materials))
    for preset in ("metal", "sand", "snow", "plasticine", "bread", "cookie", "toothpaste", "honey", "water",
                   "rigid", "rubber"):
        def build(preset=preset):
            return _cube(), material_preset(preset), Conditions(_ground()), _settings()
        out.append(StressCase(f"preset {preset}, dropped", "material", build, quick=preset in ("water", "metal")))
    for f in (1e-3, 1.0, 1e3, 1e6, 1e9):
        def build(f=f):
            return (_cube(), material_preset("jelly"),
                    Conditions(_ground() + [Force((f, f, 0.0), t_start=0.0, t_end=0.05)]), _settings(frames=LOAD_FRAMES))
        out.append(StressCase(f"force {f:.0e} N for 0.05 s", "load", build, quick=f in (1e3, 1e9)))
    for tq in (1e-3, 1.0, 1e3, 1e6):
        def build(tq=tq):
            return (_cube(), material_preset("jelly"),
                    Conditions(_ground() + [Torque((0.0, tq, 0.0), t_start=0.0, t_end=0.05)]), _settings(frames=LOAD_FRAMES))
        out.append(StressCase(f"torque {tq:.0e} N·m for 0.05 s", "load", build, quick=tq == 1.0))
    for v in (10.0, 300.0, 1e3, 1e5):
        def build(v=v):
            return (_cube(), material_preset("rubber"),
                    Conditions(_ground() + [InitialVelocity((v, -v, 0.0))]), _settings())
        out.append(StressCase(f"thrown at {v:.0e} m/s into the walls", "load", build, quick=v == 1e5))

    def jelly_hit(conds, margin):
        def build():
            return (gaussian_box((-0.05, 0.02, -0.05), (0.05, 0.12, 0.05), (10, 10, 10)), material_preset("jelly"),
                    Conditions([Ground(0.0, "slip"), Walls("slip")] + conds),
                    _settings(frames=12, grid_res=12, domain_margin=margin))
        return build
    # Issue 22: these crushed the jelly flat (det F ~ 1e-12) while mass and energy checks passed.
    for v in (10.0, 30.0):
        out.append(StressCase(f"jelly thrown at {v:g} m/s into a slip wall", "load",
                              jelly_hit([InitialVelocity((v, -v, 0.0))], 0.5)))
    out.append(StressCase("jelly shoved by 500 N for 0.2 s into a wall 4 cm away", "load",
                          jelly_hit([Force((500.0, 0.0, 0.0), t_start=0.0, t_end=0.2)], 0.4)))

    def sheet():
        g = gaussian_box((-0.1, 0.05, -0.1), (0.1, 0.05, 0.1), (12, 1, 12), sigma=0.005)
        return g, material_preset("jelly"), Conditions(_ground()), _settings(grid_res=12)
    out.append(StressCase("one-cell-thin sheet falling flat", "geometry", sheet, quick=True))

    def rod():
        g = gaussian_box((-0.15, 0.05, 0.0), (0.15, 0.05, 0.0), (30, 1, 1), sigma=0.004)
        return g, material_preset("rubber"), Conditions(_ground()), _settings(grid_res=24)
    out.append(StressCase("one-cell-thin rod", "geometry", rod))

    def touching(contact):
        def build():
            return (_cube(lift=0.02), material_preset("jelly"),
                    Conditions([Ground(0.0, contact), Walls(contact, 0.3), InitialVelocity((2.0, 0.0, 2.0))]),
                    _settings(domain_margin=0.0))
        return build
    for contact in ("sticky", "slip", "friction"):
        out.append(StressCase(f"touching {contact} walls and ground, pushed into them", "geometry",
                              touching(contact), quick=contact == "friction"))

    def two_stiff():
        a = _cube(lift=0.17)
        a.object_ids = torch.zeros(len(a), dtype=torch.int64)
        b = _cube(lift=0.02)
        b.object_ids = torch.ones(len(b), dtype=torch.int64)
        mats = [material_preset("metal"), material_preset("jelly", E=1e3)]
        return Gaussians.cat([a, b]), mats, Conditions(_ground()), _settings(frames=6)
    out.append(StressCase("metal block dropped on soft jelly", "geometry", two_stiff))

    def long_spin(frames):
        def build():
            return (_cube(), material_preset("jelly", E=1e5),
                    Conditions([Gravity((0.0, 0.0, 0.0)), InitialVelocity(angular_velocity=(0.0, 3.0, 1.0))]),
                    _settings(frames=frames, grid_res=4, min_substeps=2))
        return build
    out.append(StressCase("300 frames of free spin", "long run", long_spin(300), quick=True))
    out.append(StressCase("3000 frames of free spin", "long run", long_spin(3000)))

    def long_bounce():
        return (_cube(lift=0.2), material_preset("rubber"), Conditions(_ground()), _settings(frames=2000))
    out.append(StressCase("2000 frames: bouncing until at rest", "long run", long_bounce))

    def fixed(dt):
        def build():
            return _cube(), material_preset("jelly"), Conditions(_ground()), _settings(fixed_dt=dt)
        return build
    out.append(StressCase("fixed_dt 1e-2 s (far above the CFL limit)", "time step", fixed(1e-2), quick=True))
    out.append(StressCase("fixed_dt 1e-4 s (PhysGaussian's)", "time step", fixed(1e-4)))
    for cfl in (0.7, 0.9):
        def build(cfl=cfl):
            return _cube(), material_preset("rubber"), Conditions(_ground()), _settings(cfl=cfl)
        out.append(StressCase(f"cfl {cfl:g}", "time step", build, quick=cfl == 0.9))

    def invalid(**kw):
        def build():
            return _cube(), material_preset("jelly", **kw), Conditions(_ground()), _settings()
        return build
    out.append(StressCase("ν = 0.5 (incompressible)", "invalid input", invalid(nu=0.5), quick=True))
    out.append(StressCase("E = -1", "invalid input", invalid(E=-1.0)))
    out.append(StressCase("ρ = NaN", "invalid input", invalid(density=float("nan"))))
    return out


def run_matrix(quick: bool = False, progress=None) -> list[StressOutcome]:
    chosen = [c for c in cases() if c.quick or not quick]
    results = []
    for i, case in enumerate(chosen):
        if progress:
            progress(i, len(chosen), case.name)
        results.append(run_case(case))
    return results


def summary(results: list[StressOutcome]) -> dict:
    return {s: sum(r.status == s for r in results) for s in ("completed", "refused", "failed")}


def markdown(results: list[StressOutcome], machine: str) -> str:
    s = summary(results)
    lines = ["## Results", "",
             f"{len(results)} cases: **{s['completed']} completed, {s['refused']} refused, {s['failed']} failed**. "
             f"Machine: {machine}.", "",
             "| group | case | outcome | s | detail |", "|---|---|---|---:|---|"]
    for r in results:
        reason = r.reason.replace("|", "/").replace("\n", " ")
        if len(reason) > 300:
            reason = reason[:297] + "..."
        lines.append(f"| {r.group} | {r.name} | {r.status} | {r.seconds:.1f} | {reason} |")
    return "\n".join(lines)
