"""The load schedule: a scene's forces, torques and anchors compiled once into per-particle arrays.

``LoadSchedule.compile`` turns the time-windowed Conditions (Force, Torque, Anchor) into typed
terms that hold what the solver needs (a force's per-particle field, a torque's vector and
acceleration bound, an anchor's particles and velocity). During the run the frame loop asks which
terms are active at time t (``active``), when that next changes (``next_edge``), and hands a
change to the solver (``apply``); nothing is re-derived from the Conditions after the start.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence, Union

import numpy as np

from ..types.conditions import Anchor, Conditions, Force, Torque

TIME_EPS = 1e-12  # s: a window edge closer than this to t counts as passed


@dataclass(frozen=True)
class ForceTerm:
    """A total force spread over its region in proportion to mass: ``field`` (P,3) N, float64."""

    field: np.ndarray
    t_start: float
    t_end: float

    def peak_accel(self, mass: np.ndarray) -> float:
        return float((np.linalg.norm(self.field, axis=1) / mass).max())


@dataclass(frozen=True)
class TorqueTerm:
    """Torque ``slot`` (the bit of the solver's torque mask): its vector (N·m) and a bound on the
    acceleration |α × r| it gives its region at rest."""

    slot: int
    vector: tuple
    accel_bound: float
    t_start: float
    t_end: float


@dataclass(frozen=True)
class AnchorTerm:
    """Particles ``held`` (P,) bool, moved at ``velocity`` (m/s) while the window lasts."""

    held: np.ndarray
    velocity: tuple
    t_start: float
    t_end: float


Term = Union[ForceTerm, TorqueTerm, AnchorTerm]


def torque_accel_bound(x: np.ndarray, mass: np.ndarray, vector) -> float:
    """|I⁻¹τ| times the region's largest radius about its centre of mass: a bound on |α × r|."""
    m = mass.astype(np.float64)
    r = x - (x * m[:, None]).sum(0) / m.sum()
    inertia = np.eye(3) * (m * (r * r).sum(1)).sum() - (r.T * m) @ r
    alpha = np.linalg.norm(np.linalg.solve(inertia, np.asarray(vector)))
    return alpha * float(np.linalg.norm(r, axis=1).max())


class LoadSchedule:
    """The forces, torques and anchors of a run, in that order (the order the solver sums them)."""

    def __init__(self, n_particles: int, forces: Sequence[ForceTerm] = (), torques: Sequence[TorqueTerm] = (),
                 anchors: Sequence[AnchorTerm] = ()):
        self.n = int(n_particles)
        self.forces = tuple(forces)
        self.torques = tuple(torques)
        self.anchors = tuple(anchors)
        self.terms: tuple[Term, ...] = self.forces + self.torques + self.anchors

    @classmethod
    def compile(cls, conditions: Conditions, x0: np.ndarray, mass: np.ndarray, torque_mask: np.ndarray,
                anchor_sel: Sequence[np.ndarray], region: Callable[[object, str], np.ndarray]) -> "LoadSchedule":
        """``mass``: the solver's particle masses; ``torque_mask``: bit k marks torque k's region;
        ``anchor_sel``: each Anchor's particles; ``region(region, what)`` selects a region's particles."""
        forces = []
        for force in conditions.of(Force):
            sel = region(force.region, "force")
            m = mass[sel].astype(np.float64)
            f = np.zeros((x0.shape[0], 3))
            f[sel] = np.asarray(force.vector)[None, :] * (m / m.sum())[:, None]
            forces.append(ForceTerm(f, force.t_start, force.t_end))
        torques = []
        for k, tq in enumerate(conditions.of(Torque)):
            sel = (torque_mask >> k) & 1 == 1
            torques.append(TorqueTerm(k, tq.vector, torque_accel_bound(x0[sel], mass[sel], tq.vector),
                                      tq.t_start, tq.t_end))
        anchors = [AnchorTerm(sel, a.velocity, a.t_start, a.t_end) for a, sel in zip(conditions.of(Anchor), anchor_sel)]
        return cls(x0.shape[0], forces, torques, anchors)

    # -- bounds the run's cost check needs ----------------------------------------------------
    def peak_accel(self, mass: np.ndarray) -> float:
        """Every force and torque at once: a bound on the acceleration they give any particle."""
        return sum(f.peak_accel(mass) for f in self.forces) + sum(t.accel_bound for t in self.torques)

    def impulse_speed(self, x: np.ndarray, mass: np.ndarray) -> float:
        """The speed the forces and torques would give the whole scene if nothing stopped them (m/s): each
        force's impulse over the scene's mass, each torque's angular impulse through the scene's inertia
        times its largest radius; summed. An estimate from below of the speeds the run must resolve (a load
        on part of a body moves that part faster), which the cost check turns into substeps per frame."""
        m = mass.astype(np.float64)
        if not (self.forces or self.torques) or m.sum() <= 0:
            return 0.0
        v = sum(float(np.linalg.norm(f.field.sum(0))) * max(f.t_end - f.t_start, 0.0) for f in self.forces) / m.sum()
        if self.torques:
            r = x - (x * m[:, None]).sum(0) / m.sum()
            inertia = np.eye(3) * (m * (r * r).sum(1)).sum() - (r.T * m) @ r
            reach = float(np.linalg.norm(r, axis=1).max())
            for t in self.torques:
                try:
                    omega = np.linalg.norm(np.linalg.solve(inertia, np.asarray(t.vector, float)))
                except np.linalg.LinAlgError:  # a line of particles: no bound from below
                    continue
                v += float(omega) * max(t.t_end - t.t_start, 0.0) * reach
        return v if math.isfinite(v) else 0.0

    def peak_anchor_speed(self) -> float:
        return max([float(np.linalg.norm(a.velocity)) for a in self.anchors], default=0.0)

    # -- time windows -------------------------------------------------------------------------
    def active(self, t: float) -> tuple[int, ...]:
        """Indices (into ``terms``) of the terms acting at time t."""
        return tuple(i for i, term in enumerate(self.terms) if term.t_start <= t < term.t_end)

    def next_edge(self, t: float) -> float:
        """The next time after t at which a term starts or ends (inf: none)."""
        edges = [e for term in self.terms for e in (term.t_start, term.t_end) if e > t + TIME_EPS]
        return min(edges) if edges else math.inf

    def pending(self, t: float) -> bool:
        """Is any term active now or still to come?"""
        return any(term.t_end > t + TIME_EPS for term in self.terms)

    # -- handing a set of active terms to the solver ------------------------------------------
    def apply(self, solver, active: tuple[int, ...]) -> None:
        """Set the solver's external forces, torques and anchors to those of the ``active`` terms."""
        now = [self.terms[i] for i in active]
        f = np.zeros((self.n, 3))
        for term in now:
            if isinstance(term, ForceTerm):
                f += term.field
        solver.set_external_forces(f)
        taus = np.zeros((max(len(self.torques), 1), 3))
        bound = 0.0
        for term in now:
            if isinstance(term, TorqueTerm):
                taus[term.slot] = term.vector
                bound += term.accel_bound
        solver.set_torques(taus, bound)
        held = np.zeros(self.n, bool)
        velocity = np.zeros((self.n, 3))
        for term in now:
            if isinstance(term, AnchorTerm):
                held |= term.held
                velocity[term.held] = term.velocity
        solver.set_anchors(held, velocity)
