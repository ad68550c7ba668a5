"""Building blocks for the accuracy cases: particle lattices, boxes, and a stepper that samples.

The cases drive ``MPMSolver`` directly (not ``simulate``) so that their geometry, grid and clamps are
exactly the analytic problem's: a bar of length L is L long, a column stands against a wall.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from typing import Callable, Optional, Sequence

import numpy as np

from ..sim.mpm import PAD, Domain, MPMSolver
from ..types.conditions import Ground


@dataclass
class CaseResult:
    """One comparison with an analytic or published answer."""

    name: str
    quantity: str
    measured: float
    expected: float
    error: float  # relative unless ``absolute`` says otherwise
    tolerance: float
    why: str  # where the tolerance comes from
    seconds: float = 0.0
    absolute: bool = False
    details: dict = field(default_factory=dict)

    @property
    def passed(self) -> bool:
        return bool(np.isfinite(self.error) and abs(self.error) <= self.tolerance)

    def as_dict(self) -> dict:
        d = asdict(self)
        d["passed"] = self.passed
        return d


def lattice(lo: Sequence[float], hi: Sequence[float], spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Particles at the centres of a cubic lattice filling the box [lo, hi]; returns (x, volume).
    The box is rounded to a whole number of spacings on each axis."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    n = np.maximum(1, np.round((hi - lo) / spacing).astype(int))
    axes = [lo[a] + (np.arange(n[a]) + 0.5) * spacing for a in range(3)]
    x = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return x, np.full(len(x), spacing**3)


def ball(centre: Sequence[float], radius: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    c = np.asarray(centre, float)
    x, vol = lattice(c - radius, c + radius, spacing)
    keep = np.linalg.norm(x - c, axis=1) <= radius
    return x[keep], vol[keep]


def box_domain(lo: Sequence[float], hi: Sequence[float], dx: float, ground: Optional[Ground] = None) -> Domain:
    """A grid whose outermost constrained nodes lie on the planes of [lo, hi]: nodes below index PAD
    (and from dims - PAD up) obey the walls, the ground node is index PAD. With ``ground`` the
    floor is at lo[1]."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    origin = lo - (PAD - 1) * dx
    if ground is not None:
        origin[1] = lo[1] - PAD * dx
    dims = tuple(int(round((hi[a] - origin[a]) / dx)) + PAD for a in range(3))
    return Domain(origin=origin, dx=float(dx), dims=dims, ground_node=PAD if ground is not None else -1)


def run_sampled(solver: MPMSolver, times: Sequence[float], observe: Callable[[MPMSolver], object],
                max_dt: float = math.inf) -> list:
    """Advance to each of ``times`` (ascending, s), with steps no longer than ``max_dt``, and
    return ``observe(solver)`` at each."""
    out = []
    for t in times:
        while solver.t < t - 1e-12:
            solver.substep(min(solver.stable_dt(), max_dt, t - solver.t))
        out.append(observe(solver))
    return out


def momentum(solver: MPMSolver, about: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Total linear momentum, angular momentum about ``about`` (default: the centre of mass) and
    the centre of mass.

    The angular momentum is APIC's conserved one: Σ m r × v plus each particle's affine part
    m D ε:Cᵀ, D = dx²/4 for quadratic B-splines (a spinning particle's share, ½ m dx² ω).
    """
    m = solver.mass_np.astype(np.float64)
    x = solver.positions().astype(np.float64)
    v = solver.velocities().astype(np.float64)
    C = solver.C.numpy().astype(np.float64)
    com = (x * m[:, None]).sum(0) / m.sum()
    c = com if about is None else np.asarray(about, float)
    axial = np.stack([C[:, 2, 1] - C[:, 1, 2], C[:, 0, 2] - C[:, 2, 0], C[:, 1, 0] - C[:, 0, 1]], 1)
    affine = 0.25 * solver.domain.dx**2 * (m[:, None] * axial).sum(0)
    return (m[:, None] * v).sum(0), (m[:, None] * np.cross(x - c, v)).sum(0) + affine, com


def timed(fn):
    """Decorator: fill CaseResult.seconds with the case's wall time."""
    def wrapper(*args, **kwargs):
        t0 = time.perf_counter()
        res = fn(*args, **kwargs)
        for r in (res if isinstance(res, list) else [res]):
            r.seconds = time.perf_counter() - t0
        return res
    wrapper.__name__ = fn.__name__
    wrapper.__doc__ = fn.__doc__
    return wrapper
