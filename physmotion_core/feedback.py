"""What the user is told before the wait and after it.

Before simulating: the object's mass and material, and what each push, twist or throw will roughly do,
from Newton's laws on the whole body (no simulation): the change of speed Δv = F·Δt / m, whether the
push beats static friction μ·m·g, whether it can tip the object over its base edge (F·h > m·g·b, the
quasi-static tipping condition about the edge it pushes towards; a soft body leans into the push first
and tips with less: ``lean``), and whether the estimated travel
leaves the frame. These are estimates for a body that stays in one piece; they say what to change when
a push is far too weak or far too strong, so that nobody waits minutes for a video in which nothing
moves, or in which the object flies off screen. A mask in separate pieces lifts to separate bodies
(``pieces``): each piece that nothing holds up is named (it falls), and a push on one piece is
estimated on that piece.

After simulating: a warning when nothing moved visibly, and when the object, or a separate piece of
it, left the frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch

from .types.camera import Camera
from .types.conditions import Anchor, Conditions, Force, Ground, InitialVelocity, Torque
from .types.material import Material
from .types.settings import SimSettings

#: Below this many pixels of largest motion in the input view, "nothing moved" is reported.
STILL_PX = 1.0
#: The object counts as having left the frame when this fraction of it projects outside the image.
LEFT_FRACTION = 0.5


@dataclass
class BodyFacts:
    """The filled object: particle rest positions (P, 3) and masses (P,) in SI units, the simulation's grid
    cell size ``dx`` (m; 0 when unknown), and whether the scene is one object (``single``): only then are
    its separate pieces looked for (``pieces``; several objects are meant to be apart)."""

    x: np.ndarray
    mass: np.ndarray
    dx: float = 0.0
    single: bool = True

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
                         ground, conform=[material.model == "rigid"] * len(objects))  # as simulate() fills
    return BodyFacts(parts.x, (parts.volume * float(material.density)).astype(np.float64), float(res.dx),
                     len(objects) == 1)


#: A separate piece is reported (before: it falls; after: it left the frame) from this share of the mass.
PIECE_MIN_SHARE = 0.02


def piece_labels(x: np.ndarray, dx: float) -> np.ndarray:
    """(P,) the separate body each particle belongs to, 0..n-1 from the most particles down; all zeros
    when ``dx`` (the grid cell, which says the object is one to be looked at) is 0.

    The simulator fills an object with particles on a lattice (``sim.fill``: voxel centres, jittered by a
    tenth of the spacing), and particles in face-, edge- or corner-neighbouring voxels are one body here;
    a gap of one empty voxel separates two. A mask in pieces (a head that the collar left out, so that
    only the photo joins it to the suit) lifts to bodies that nothing binds together: MPM couples them
    only where they press on each other, and a push or gravity parts them. The lattice's spacing is
    measured from the particles (the median distance to the nearest one)."""
    from scipy import ndimage

    x = np.asarray(x, np.float64)
    if len(x) < 2 or not dx > 0:
        return np.zeros(len(x), np.int64)
    spacing = lattice_spacing(x)
    if not spacing > 0:
        return np.zeros(len(x), np.int64)
    idx = np.rint((x - x.min(0)) / spacing).astype(np.int64)
    occ = np.zeros(tuple(idx.max(0) + 1), bool)
    occ[tuple(idx.T)] = True
    lab, n = ndimage.label(occ, structure=np.ones((3, 3, 3), bool))
    raw = lab[tuple(idx.T)] - 1
    order = np.argsort(-np.bincount(raw, minlength=n), kind="stable")
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n)
    return rank[raw]


@dataclass
class Piece:
    """A separate body of the object: its particles (``sel``), mass, and what holds it up."""

    sel: np.ndarray
    mass: float
    share: float
    held: bool  # a hold (the frame's edge, an anchor) reaches it
    grounded: bool  # it stands on the ground
    resting: bool  # it lies on a piece that is held up

    @property
    def supported(self) -> bool:
        return self.held or self.grounded or self.resting


def pieces(facts: BodyFacts, conditions: Conditions, camera: Optional[Camera] = None,
           min_share: float = PIECE_MIN_SHARE) -> list[Piece]:
    """The object's separate bodies (``piece_labels``) of at least ``min_share`` of its mass (a mask's stray
    specks are not worth a word, and there are at most 1/min_share of the others), in order of particle
    count, and for each whether an anchor holds it, it stands on the ground (its lowest particle within two
    cells of it), or it lies on a piece that is held up (a particle of that piece at most two cells under one
    of its own, within a cell sideways)."""
    from scipy import ndimage

    labels = piece_labels(facts.x, facts.dx)
    n = int(labels.max()) + 1 if len(labels) else 0
    total = max(facts.total_mass, 1e-30)
    held_sel = np.zeros(len(facts.x), bool)
    for a in conditions.of(Anchor):
        held_sel |= _region_sel(a, facts, camera)
    ground = conditions.ground()
    masses = np.bincount(labels, weights=facts.mass, minlength=n)
    held = np.bincount(labels, weights=held_sel.astype(np.float64), minlength=n) > 0
    lowest = np.full(n, np.inf)
    np.minimum.at(lowest, labels, facts.x[:, 1])
    out = []
    for k in range(n):
        if masses[k] < min_share * total:
            continue
        grounded = ground is not None and float(lowest[k]) <= float(ground.height) + 2 * facts.dx
        out.append(Piece(labels == k, float(masses[k]), float(masses[k]) / total, bool(held[k]), bool(grounded),
                         False))
    if len(out) > 1:
        idx = np.floor((facts.x - facts.x.min(0)) / facts.dx).astype(np.int64)
        shape = tuple(idx.max(0) + 4)
        # the cells a held-up piece carries: up to two cells above it, one to each side
        reach = np.zeros((3, 3, 3), bool)
        reach[:, 1:, :] = True
        origin = (0, -1, 0)  # with this origin the structure covers 1..2 cells upwards (y grows up)
        changed = True
        while changed:
            changed = False
            occ = np.zeros(shape, bool)
            for p in out:
                if p.supported:
                    occ[tuple(idx[p.sel].T)] = True
            carried = ndimage.binary_dilation(occ, structure=reach, origin=origin)
            for p in out:
                if not p.supported and carried[tuple(idx[p.sel].T)].any():
                    p.resting, changed = True, True
    return out


def _where(sel: np.ndarray, facts: BodyFacts, camera: Optional[Camera]) -> str:
    """Where a piece is in the photo: the box in pixels of its camera-facing quarter (the surface the photo
    shows: the far side of a body close to the camera projects well inside it), or nothing without a
    camera."""
    if camera is None or not sel.any():
        return ""
    uv, z = camera.project(torch.from_numpy(facts.x[sel].astype(np.float32)))
    z = z.numpy()
    front = z <= z.min() + 0.25 * (z.max() - z.min())
    u, v = uv[front, 0].numpy(), uv[front, 1].numpy()
    return f" at x {u.min():.0f}..{u.max():.0f}, y {v.min():.0f}..{v.max():.0f} px"


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


def frame_room(facts: BodyFacts, camera: Optional[Camera], top: bool = False):
    """Metres of free room, at the object's depth, between the object and the frame's left and right
    edges (None without a camera); with ``top``, also above it, up to the frame's top edge."""
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
    sides = float(u.min()) * m_per_px, float(camera.width - u.max()) * m_per_px
    return sides + (float(uv[:, 1].min()) * m_per_px,) if top else sides


#: Fewer grid cells than THIN_CELLS across the object's narrowest side make it bend too easily; WANT_CELLS is
#: what the advice aims for. Measured with the validation's cantilever (``validate.cases.cantilever``: L/h = 10,
#: sagging under its own weight, against Euler-Bernoulli; docs/accuracy.md): 1 cell thick +27 %, 2 cells
#: +5.0 %, 3 cells +2.2 %, 4 cells +2.1 % (shear, which beam theory leaves out, is about 1-2 % of that).
THIN_CELLS = 2.0
WANT_CELLS = 3.0


def thin_line(facts: BodyFacts) -> str:
    """A sentence when the object is under ``THIN_CELLS`` grid cells across its narrowest side (a pole, a wire, a
    thin branch: the grid resolution counts cells across the object's largest extent), with the grid resolution
    that gives it ``WANT_CELLS`` and what that costs; "" otherwise."""
    if not facts.dx > 0 or len(facts.x) < 2:
        return ""
    ext = np.ptp(facts.x, axis=0) + facts.dx / 2  # particle centres lie half a spacing inside the surface
    k = int(np.argmin(ext))
    cells = float(ext[k]) / facts.dx
    if cells >= THIN_CELLS:
        return ""
    res_now = float(ext.max()) / facts.dx
    want = int(math.ceil(res_now * WANT_CELLS / cells))
    r = want / res_now
    side = ("width", "height", "depth")[k]
    return (f"resolution: the object is only {cells:.1f} grid cells across its narrowest side (its {side}), so it "
            f"bends too easily (a beam 1 cell thick sags 27 % more than beam theory, 2 cells 5 %, 3 cells 2 %). A "
            f"grid resolution of {want} cells across the object gives it {WANT_CELLS:.0f} (about {r ** 3:.0f}x the "
            f"particles and {r ** 4:.0f}x the run time).")


#: A run of at least this many particle-substeps is said to be long before it starts (``steps_line``): the bundled
#: demo's 4,201 substeps of 38,157 particles (1.6e8) take about half a minute on 2 CPU cores (README), so this is
#: several minutes there.
LONG_RUN_WORK = 2.0e9
#: What makes a long run quicker: said before it (``steps_line``) and when its pace says so (``sim.simulate._Pace``).
QUICKER_RUN = ("a coarser grid (quality draft, or a lower grid_res), a softer material (lower E; or the rigid material "
               "for a body that should not bend, whose step does not depend on E), a larger object height (the steps "
               "grow with the grid's cells), or fewer frames")


def steps_line(material: Material, facts: BodyFacts, clip_s: float, cfl: float = SimSettings.cfl,
               conditions: Optional[Conditions] = None) -> str:
    """A sentence before the wait when the material's wave speed on the grid makes the run long: the substeps it
    needs (clip / (cfl dx / (c + v)), v the fastest start of ``conditions``' throws: their speed plus their spin
    at half the object's extent), of how many particles, what sets the step, and what makes it quicker; "" for a
    run under LONG_RUN_WORK particle-substeps (the step the run starts with: forces and speeds reached later can
    only shorten it)."""
    c = material.wave_speed()
    if not (facts.dx > 0 and clip_s > 0 and c > 0 and len(facts.x)):
        return ""
    half = float(np.ptp(facts.x, axis=0).max()) / 2
    throws = conditions.of(InitialVelocity) if conditions is not None else []
    v = max((float(np.linalg.norm(t.velocity)) + float(np.linalg.norm(t.angular_velocity)) * half for t in throws),
            default=0.0)
    step = cfl * facts.dx / (c + v)
    steps = clip_s / step
    if steps * len(facts.x) < LONG_RUN_WORK:
        return ""
    return (f"run time: this needs about {steps:,.0f} substeps of {len(facts.x):,} particles (steps of {step:.2g} s: "
            f"{material.name} carries waves at {c:.3g} m/s on a grid of {facts.dx * 1000:.3g} mm), a long run on a "
            f"CPU (the bundled demo's 4,201 substeps of 38,157 particles take about half a minute on 2 cores); it "
            f"says how long once it has run a few seconds. Quicker: {QUICKER_RUN}.")


def _fmt_pa(p: float) -> str:
    return f"{p / 1000:.3g} kPa" if p >= 1000 else f"{p:.3g} Pa"


def flow_line(material: Material, facts: BodyFacts, g: float) -> str:
    """For a liquid or a paste (``fluid``, ``viscoplastic``): whether the object keeps its shape under its own
    weight, and if not how fast it slumps; "" for other materials.

    The weight's stress at the base of a body h tall is ρ·g·h; a paste yields where its von Mises stress passes
    σ_y. Measured through the solver (upright cylinders on rough ground, docs/accuracy.md): toothpaste twice as
    tall as wide at ρ·g·h = 1.5 σ_y sags 0.8 %, at 2 σ_y 7.5 % and still creeping; one as wide as tall at 4 σ_y
    slumps to 70 % of its height. Honey, water and toothpaste 0.3 m tall fall nearly freely, their top at
    0.52-0.54 of its height after 0.75·√(2h/g); honey 3 cm tall, slowed by its viscosity (μ/(ρ·g·h) a third of
    √(2h/g)), is still at 0.79 then and takes about four times as long."""
    if material.model not in ("fluid", "viscoplastic") or len(facts.x) < 2 or not g > 0:
        return ""
    h = float(np.ptp(facts.x[:, 1])) + facts.dx / 2
    if not h > 0:
        return ""
    rho = float(material.density)
    sigma = rho * g * h
    yield_stress = float(material.yield_stress) if material.model == "viscoplastic" else 0.0
    name = material.name
    if sigma <= 1.5 * yield_stress:
        return (f"flow: {name} keeps its shape under its own weight at this size (ρ·g·h = {_fmt_pa(sigma)} at its "
                f"base, within 1.5 times its yield stress {_fmt_pa(yield_stress)}).")
    if sigma <= 4 * yield_stress:
        return (f"flow: {name} sags under its own weight at this size (ρ·g·h = {_fmt_pa(sigma)} at its base, "
                f"{sigma / yield_stress:.2g}x its yield stress) and settles lower, but does not run away.")
    t_fall = math.sqrt(2 * h / g)
    slow = float(material.viscosity) / (rho * g * h) / t_fall
    why = (f"its yield stress, {_fmt_pa(yield_stress)}, is far below the weight's {_fmt_pa(sigma)} at its base"
           if yield_stress > 0 else "it has no shape of its own")
    when = (f"its top falls to half its height in about {0.75 * t_fall:.2g} s, nearly a free fall" if slow < 0.05
            else f"its viscosity ({material.viscosity:.3g} Pa·s) slows it: its top takes longer than "
                 f"{0.75 * t_fall:.2g} s to fall to half its height")
    return f"flow: {name} flows under its own weight from the first frame ({why}); {when}."


#: The base band: a body's particles within this share of its height of its lowest. ``lean``'s beam is clamped at
#: its top and ``balance`` takes its footprint; the tipping lever (``tipping``) uses the lowest layer only.
BASE_BAND = 0.05
#: Materials whose elasticity lets a pushed body lean before it tips (``lean``); for a rigid body, a
#: liquid, a paste or sand the rigid estimate stays (sand and pastes slump rather than tip).
LEAN_MODELS = ("fixed_corotated", "neo_hookean", "fracture", "snow", "von_mises", "plasticine")
#: A sliding body whose turning moment comes within this share of the one that keeps it up may tip.
SLIDE_TIP_MARGIN = 0.8
#: The lean is named only when it lowers the tipping force by more than this share.
LEAN_MATTERS = 0.1


def lattice_spacing(x: np.ndarray) -> float:
    """The spacing of the simulator's particle lattice (``sim.fill``), measured as the median distance from a
    particle to its nearest neighbour; 0 for fewer than two particles."""
    from scipy.spatial import cKDTree

    if len(x) < 2:
        return 0.0
    d, _ = cKDTree(x).query(x, k=2)
    return float(np.median(d[:, 1]))


@dataclass
class Lean:
    """A soft body's sideways give: ``compliance`` (m/N), how far its centre of mass moves per newton of push,
    its own weight's sway included; ``buckling``, its weight over the weight that would buckle it (Greenhill's
    (L/L_c)³ for a uniform column): at 1 or more it cannot stand up under its own weight (``compliance`` is then
    inf)."""

    compliance: float
    buckling: float
    at_load: float = 0.0  # m/N: how far the loaded particles themselves move (load-weighted), per newton


def lean(x: np.ndarray, mass: np.ndarray, material: Material, direction: np.ndarray, load: np.ndarray,
         g: float = 9.81) -> Lean:
    """How far a body standing on the ground leans along the horizontal unit ``direction`` (x, z) under a push
    spread over its particles in the proportions ``load`` (summing to 1), and whether its own weight can hold
    it up at all.

    The body above its base band (``BASE_BAND``) is a vertical beam clamped at the band, in slices one particle
    spacing thick, each with its own area A and second moment I about its centroid across ``direction``
    (particle volumes m/ρ): Timoshenko's beam, bending M/(E·I) and shear V/(κ·G·A), κ = 5/6, integrated up
    from the base. As it leans, the weight above each slice pulls sideways on it (g·Σ m·(u_above - u_here)),
    which the beam takes in too: the lean solves (1 - W)·u = u_push, W that weight's bend. W's largest
    eigenvalue is the weight over the buckling weight. For a uniform block of height L this gives the closed
    form L³/(20·E·I) + L/(3·κ·G·A) without the weight and Greenhill's (L/L_c)³, L_c = (7.837·E·I/q)^(1/3), q
    its weight per length (``tests/test_feedback_lean.py``). A sketch: it leaves out the base's own give and
    large deflections. Measured against the simulation in docs/accuracy.md ("Does a push tip it over?")."""
    spacing = lattice_spacing(x)
    y = x[:, 1]
    H = float(np.ptp(y)) if len(y) else 0.0
    if not spacing > 0 or not H > 0 or not material.E > 0:
        return Lean(0.0, 0.0)
    up = y > float(y.min()) + BASE_BAND * H
    if not up.any():
        return Lean(0.0, 0.0)
    vol = mass[up] / float(material.density)
    k = np.floor((y[up] - float(y[up].min())) / spacing).astype(np.int64)
    n = int(k.max()) + 1
    v = np.bincount(k, vol, n)
    across = x[up][:, [0, 2]] @ np.asarray(direction, np.float64)
    centre = np.bincount(k, vol * across, n) / np.maximum(v, 1e-30)
    inertia = np.bincount(k, vol * (across - centre[k]) ** 2, n) / spacing + v * spacing / 12.0
    area = v / spacing
    filled = v > 0
    flex = np.where(filled, 1.0 / (material.E * np.maximum(inertia, 1e-30)), 0.0)  # 1/(E·I) per slice
    w = np.bincount(k, load[up], n)
    yc = (np.arange(n) + 0.5) * spacing
    shear = np.cumsum(w[::-1])[::-1]  # the load on each slice and every slice above it
    moment = np.cumsum((w * yc)[::-1])[::-1] - shear * (yc - 0.5 * spacing)  # about each slice's bottom
    slide = np.where(filled, shear / (5.0 / 6.0 * material.mu * np.maximum(area, 1e-30)), 0.0)
    lower = np.tril(np.ones((n, n)))  # running sum up from the base
    u_push = lower @ (lower @ (moment * flex * spacing) * spacing) + lower @ (slide * spacing)
    # the weight above slice i, leaning by u_j - u_{i-1}, bends slice i: moment g·(Σ_j≥i m_j u_j - u_{i-1} Σ_j≥i m_j)
    m_slice = np.bincount(k, mass[up], n)
    above = np.triu(np.ones((n, n))) * m_slice[None, :]
    below = np.eye(n, k=-1) * (above.sum(1))[:, None]
    weight = g * (lower @ (lower * spacing) * spacing) @ (flex[:, None] * (above - below))
    ratio = float(np.max(np.abs(np.linalg.eigvals(weight)))) if n else 0.0
    if ratio >= 1.0:
        return Lean(math.inf, ratio)
    u = np.linalg.solve(np.eye(n) - weight, u_push)
    return Lean(float((m_slice * u).sum() / max(float(mass.sum()), 1e-30)), ratio, float((w * u).sum()))


def dynamic_factor(mass: float, compliance: float, duration: float) -> float:
    """How far past its static lean a body swings under a push switched on at once and held for ``duration``:
    the peak of an undamped oscillator (period 2π·√(m·c)) under a rectangular pulse, 2·sin(π·t/T) up to 2."""
    if not compliance > 0 or not mass > 0:
        return 1.0
    period = 2.0 * math.pi * math.sqrt(mass * compliance)
    return 2.0 * math.sin(min(math.pi / 2.0, math.pi * max(duration, 0.0) / period))


@dataclass
class Tipping:
    """Where a sideways push tips a body standing on the ground: ``b`` (m), from its centre of mass to the edge of
    its base it is pushed towards; ``h`` (m), the height the push acts at, and ``h_com`` the centre of mass's
    (both above its lowest point); ``need`` (N), the rigid body's tipping
    force m·g·b/h; ``lean_per_n`` (m/N), how far a soft body's centre of mass leans towards that edge per newton
    (static lean times the swing of a sudden push; 0 for a rigid body); ``soft_need`` (N), the force that tips it
    with that lean and that swing, m·g·b/(max(1, D)·h + m·g·lean_per_n) (``tipping``)."""

    b: float
    h: float
    h_com: float
    need: float
    lean_per_n: float
    soft_need: float
    buckling: float = 0.0  # the body's weight over its buckling weight (``Lean``); at 1 or more it cannot stand


def tipping(body: BodyFacts, direction: np.ndarray, sel: np.ndarray, g: float, duration: float,
            material: Optional[Material] = None) -> Tipping:
    """The tipping estimate for a push along the horizontal unit ``direction`` (x, z) on the particles ``sel``
    for ``duration`` seconds: the quasi-static condition about the base's edge, F·h > m·g·b, and for an elastic
    ``material`` (``LEAN_MODELS``) the same with the body's lean and the swing of a push switched on at once, which
    carries the push's moment to the base through the body's spring as it does the lean: D·F·h + m·g·D·c·F > m·g·b
    (``lean``'s compliance c, ``dynamic_factor`` D, its moment part at least 1). Measured against the simulation in
    docs/accuracy.md ("Does a push tip it over?"): with the moment's swing the forecast agreed with 20 of 23 runs,
    without it 19; the misses are soft bodies that tip from below 0.6 of even this force."""
    m = body.total_mass
    base_y = float(body.x[:, 1].min())
    # What it stands on: its lowest layer of particles (the lattice is jittered by a tenth of its spacing), whose
    # footprint reaches half a spacing past their centres. A rounded bottom stands on a narrow layer and tips
    # sooner than a band of its height would say (docs/accuracy.md: the rigid disc).
    spacing = lattice_spacing(body.x)
    base = body.x[body.x[:, 1] <= base_y + 0.5 * spacing]
    com = body.com
    d = np.asarray(direction, np.float64)
    h = float(body.x[sel, 1].mean()) - base_y if sel.any() else float(com[1]) - base_y
    b = max(0.0, float((base[:, [0, 2]] @ d).max() - com[[0, 2]] @ d) + 0.5 * spacing if len(base) else 0.0)
    need = m * g * b / max(h, 1e-9)
    lean_per_n, soft_need, buckling = 0.0, need, 0.0
    if material is not None and material.model in LEAN_MODELS and b > 0:
        load = body.mass * sel
        give = lean(body.x, body.mass, material, d, load / max(float(load.sum()), 1e-30), g)
        buckling = give.buckling
        if math.isinf(give.compliance):
            lean_per_n, soft_need = math.inf, 0.0
        else:
            swing = dynamic_factor(m, give.compliance, duration)
            lean_per_n = swing * give.compliance
            # the push's moment too reaches the base through the body's spring: switched on at once, the base's
            # pressure swings past its static share like the lean (the heel lifts from about half the static force)
            soft_need = m * g * b / (max(1.0, swing) * max(h, 1e-9) + m * g * lean_per_n)
    return Tipping(b, h, float(com[1]) - base_y, need, lean_per_n, soft_need, buckling)


def balance(facts: BodyFacts) -> tuple[float, np.ndarray]:
    """How far (m) the centre of mass of a body standing on the ground lies beyond the edge of what it stands on
    (0 when above it), and the particles it stands on: its base, those within ``BASE_BAND`` of its height of the
    lowest, whose footprint (convex hull in x, z) reaches half a lattice spacing past their centres."""
    from scipy.spatial import ConvexHull, QhullError

    x = facts.x
    y = x[:, 1]
    if len(x) < 2:
        return 0.0, np.ones(len(x), bool)
    on = y <= float(y.min()) + BASE_BAND * max(1e-9, float(np.ptp(y)))
    foot = x[on][:, [0, 2]].astype(np.float64)
    com = facts.com[[0, 2]]
    reach = 0.5 * (lattice_spacing(x) or facts.dx / 2)
    try:
        hull = ConvexHull(foot)
        out = float(np.max(hull.equations[:, :2] @ com + hull.equations[:, 2]))
    except (QhullError, ValueError):  # a line or a point of contact
        out = float(np.min(np.linalg.norm(foot - com, axis=1)))
    return max(0.0, out - reach), on


def balance_line(facts: BodyFacts, camera: Optional[Camera] = None) -> str:
    """A sentence when a body standing on the ground is not balanced on what it stands on (its centre of mass
    beyond its base's edge, ``balance``): it tips over under its own weight with no push. This is a mask whose
    lowest part is not what the object stands on (a spike of foliage under a building, a wheel cut off, a
    leaning object), as the lift stands the object on its lowest point; "" when balanced."""
    off, on = balance(facts)
    if not off > 0:
        return ""
    foot = facts.x[on]
    wide, deep = (float(np.ptp(foot[:, k])) + facts.dx / 2 for k in (0, 2))
    return (f"balance: it stands on its lowest part ({100 * wide:.2g} x {100 * deep:.2g} cm{_where(on, facts, camera)}) "
            f"and its "
            f"centre of mass is {100 * off:.2g} cm beyond that part's edge, so it tips over under its own weight from "
            "the first frame, without any push. If it should stand, make the box or mask end where the object stands "
            "(whatever sticks out below it is what it is stood on).")


#: A body whose weight is this share of its buckling weight or more is said to stand only just.
STAND_WARN = 0.6


def stand_line(material: Material, facts: BodyFacts, g: float, held: bool = False) -> str:
    """For an elastic solid (``LEAN_MODELS``) that is too soft for its height: a sentence saying that it cannot
    stand under its own weight (a soft column buckles: ``lean``'s weight over buckling weight, in the weaker of
    the two horizontal directions, 1 or more) and what stiffness or height lets it, or that it stands only just
    (``STAND_WARN`` or more); "" otherwise. The ratio grows as E falls (1/E) and as the body is scaled up
    (proportionally to its size: its weight grows as size³, its bending stiffness as size⁴ over a column's
    size³ lever). Checked against the simulation: a 0.3 m jelly bar 1:4 wide falls over with no push at
    E = 20 and 50 kPa and stands at 100 kPa (docs/accuracy.md). ``held``: the frame's bottom edge holds the body
    (a bust, a figure cut off below): clamped at its base, the same column, which cannot tip but folds over or sways."""
    if material.model not in LEAN_MODELS or len(facts.x) < 2 or not g > 0 or facts.total_mass <= 0:
        return ""
    share = facts.mass / facts.total_mass
    ratio = max(lean(facts.x, facts.mass, material, np.array(d, np.float64), share, g).buckling
                for d in ((1.0, 0.0), (0.0, 1.0)))
    height = float(np.ptp(facts.x[:, 1])) + facts.dx / 2
    on = " on the base the frame's bottom edge holds" if held else ""
    if ratio >= 1.0:
        return (f"stability: {material.name} this soft (E = {material.E:.3g} Pa) cannot hold up a body {height:.2g} m "
                f"tall{on}: its weight is {ratio:.2g} times what buckles it, so it "
                f"{'folds over' if held else 'bends over and falls'} from the first "
                f"frame without any push. It stands with E above about {material.E * ratio / STAND_WARN:.2g} Pa, or "
                f"at under {height * STAND_WARN / ratio:.2g} m tall (the object height).")
    if ratio >= STAND_WARN:
        return (f"stability: {material.name} this soft (E = {material.E:.3g} Pa) only just holds up a body {height:.2g} m "
                f"tall{on} (its weight is {ratio:.0%} of what buckles it): it sways far"
                f"{' under its own weight, with no push' if held else ' and tips easily'}.")
    return ""


#: A held body's bend at the push (``bend_note``) counts as folding over past this fraction of the pushed part's
#: height above the held base.
FOLD_FRACTION = 0.5


def bend_note(F: np.ndarray, fmag: float, dt: float, body: BodyFacts, sel: np.ndarray, material: Optional[Material],
              g: float) -> str:
    """For a soft body the frame's bottom edge holds (a bust, a figure cut off below) pushed sideways: how far the
    push swings the part it acts on, as ``lean``'s beam clamped at the held base (the static bend at the load times
    ``dynamic_factor``'s swing); past ``FOLD_FRACTION`` of that part's height above the base, it folds over there.
    A sketch that leaves out any hold at the frame's sides (they stiffen it: the bend is an upper estimate). '' for
    other materials or no sideways push."""
    fh = float(math.hypot(F[0], F[2]))
    if material is None or material.model not in LEAN_MODELS or fh <= 1e-12 or not sel.any():
        return ""
    load = body.mass * sel
    give = lean(body.x, body.mass, material, F[[0, 2]] / fh, load / max(float(load.sum()), 1e-30), g)
    height = float(body.x[sel, 1].mean() - body.x[:, 1].min())
    if math.isinf(give.compliance):
        return (f"{material.name} this soft cannot hold the body up on its held base: it folds over with or "
                "without the push")
    swing = dynamic_factor(body.total_mass, give.compliance, dt) * give.at_load * fh
    if swing > FOLD_FRACTION * height:
        return (f"{material.name} this soft bends about {swing:.2g} m where it is pushed, more than half of its "
                f"{height:.2g} m above the held base: it folds over there (a smaller force, a larger --radius "
                "lower down or a stiffer material keeps it up)")
    return f"it bends about {100 * swing:.2g} cm where it is pushed and springs back"


def _push_line(k: int, F: np.ndarray, fmag: float, dt: float, body: BodyFacts, g: float, ground: Optional[Ground],
               anchored: bool, camera: Optional[Camera], clip_s: float, t1: float, f, what: str,
               material: Optional[Material] = None, tilted: bool = False, clamped: bool = False) -> str:
    """What push ``k`` does to ``body`` (the whole object, or the pieces it touches); ``clamped``: the frame's
    bottom edge holds it (``bend_note``)."""
    m = body.total_mass
    room = frame_room(body, camera)
    friction_limit = None
    if ground is not None and not anchored:
        friction_limit = {"sticky": math.inf, "slip": 0.0}.get(ground.contact, float(ground.friction) * m * g)
    dv = fmag * dt / m
    head = f"force {k}: {fmag:.3g} N for {dt:.3g} s on {_fmt_mass(m)}{what}: Δv ≈ {dv:.3g} m/s if nothing held it"
    notes = []
    if anchored:
        notes.append("the object is held, so the push bends or shears it rather than moving it away")
        bend = bend_note(F, fmag, dt, body, _region_sel(f, body, camera), material, g) if clamped else ""
        if bend:
            notes.append(bend)
    fh = float(math.hypot(F[0], F[2]))
    # A round rigid body (a ball, a wheel seen face-on: ``rolls_along``) on a ground that grips rolls under any
    # sideways push: static friction turns it rather than holding it, and it does not tip over an edge.
    rolls = (ground is not None and not anchored and fh > 1e-12 and ground.contact != "slip"
             and material is not None and material.model == "rigid" and rolls_along(body, F))
    if rolls:
        grip = friction_limit / ROLL_FRICTION_SHARE
        notes.append(f"it is round: it rolls rather than slides or tips, at about {ROLL_SPEED_SHARE * dv:.3g} m/s "
                     f"(of Δv, {ROLL_SPEED_SHARE:.2g} goes into rolling; a ball)"
                     + (f"; past {grip:.3g} N ({1 / ROLL_FRICTION_SHARE:.2g}·μ·m·g) it also skids"
                        if fh > grip else ""))
    elif ground is not None and not anchored and fh > 1e-12:
        if math.isinf(friction_limit):
            notes.append("the ground is sticky: it will not slide")
        elif fh <= friction_limit:
            notes.append(f"static friction holds up to μ·m·g = {friction_limit:.3g} N, more than its {fh:.3g} N "
                         f"sideways: it will not slide (push harder than {friction_limit:.3g} N or lower the "
                         "friction to make it slide)")
        else:
            notes.append(f"it beats static friction (μ·m·g = {friction_limit:.3g} N): it slides")
        tip = tipping(body, F[[0, 2]] / fh, _region_sel(f, body, camera), g, dt, material)
        soft = tip.soft_need < (1.0 - LEAN_MATTERS) * tip.need
        # Sliding, the ground's friction is μ·m·g at most: it turns the body about its centre of mass with
        # μ·m·g·h_c, and the push with F·(h - h_c), against m·g·b (a body pushed at its centre of mass that is
        # wider than μ times its height slides rather than tips, however hard it is pushed).
        # Within SLIDE_TIP_MARGIN of m·g·b it is a toss-up (a rounded base rolls over sooner).
        sliding = friction_limit is not None and not math.isinf(friction_limit) and fh > friction_limit
        turn = fh * (tip.h - tip.h_com) + friction_limit * tip.h_com if sliding else fh * tip.h
        if tilted:
            notes.append("it tips over with or without the push: it is not balanced on what it stands on (see "
                         "'balance')")
        elif fh * tip.h > m * g * tip.b and turn > m * g * tip.b:
            notes.append(f"it can tip over (F·h = {fh * tip.h:.3g} N·m > m·g·b = {m * g * tip.b:.3g} N·m)")
        elif fh * tip.h > m * g * tip.b and turn > SLIDE_TIP_MARGIN * m * g * tip.b:
            notes.append(f"it slides and may tip over: sliding, the ground holds its base with μ·m·g = "
                         f"{friction_limit:.3g} N only, which turns it with {turn:.3g} N·m against the "
                         f"{m * g * tip.b:.3g} N·m that keep it up")
        elif fh * tip.h > m * g * tip.b and not soft:
            notes.append(f"it slides rather than tips: sliding, the ground holds its base with μ·m·g = "
                         f"{friction_limit:.3g} N only, too little to turn it over its edge")
        elif tip.buckling >= 1.0:
            notes.append(f"it falls over with or without the push: {material.name} this soft cannot hold up a body "
                         "this tall (see 'stability')")
        elif soft and fh >= tip.soft_need:
            leans = tip.lean_per_n * fh
            notes.append(f"it may tip over: a rigid body would need about {tip.need:.3g} N at that height, but "
                         f"{material.name} this soft "
                         + (f"leans about {100 * leans:.2g} cm into the push" if leans < tip.b else
                            "leans past its base's edge under this push")
                         + f" and tips from about {tip.soft_need:.3g} N")
        elif fh > 0.3 * tip.soft_need:
            notes.append(f"it rocks but does not tip (tipping needs about {tip.soft_need:.3g} N at that height"
                         + (f"; {material.name} this soft leans into the push: a rigid body would need "
                            f"{tip.need:.3g} N" if soft else "") + ")")
    if F[1] > m * g and not anchored:
        notes.append(f"it lifts off (upward {F[1]:.3g} N > its weight {m * g:.3g} N)")
    # Travel along x (the frame's width), for a free or sliding body: the push, then coasting to the
    # clip's end (kinetic friction ≈ μ slows it on a friction ground).
    if room is not None and not anchored and abs(F[0]) > 1e-12:
        mu_g = 0.0 if ground is None or ground.contact == "slip" else (
            math.inf if ground.contact == "sticky" else float(ground.friction) * g)
        a = abs(F[0]) / m - mu_g
        if rolls:  # friction turns it and takes no speed away: it rolls on to the clip's end
            a, mu_g = ROLL_SPEED_SHARE * abs(F[0]) / m, 0.0
        if a > 0:
            v = a * dt
            travel = 0.5 * a * dt * dt
            rest = max(0.0, clip_s - t1)
            travel += v * rest if mu_g == 0 else min(v * rest, v * v / (2 * mu_g))
            side = room[1] if F[0] > 0 else room[0]
            if travel > side:
                notes.append(f"it may leave the frame: about {travel:.3g} m of travel against {side:.3g} m of room "
                             f"on the {'right' if F[0] > 0 else 'left'} (use a smaller force or a shorter push)")
    return head + ("; " + "; ".join(notes) if notes else "") + "."


def forecast(conditions: Conditions, facts: BodyFacts, material: Material, *, clip_s: float,
             camera: Optional[Camera] = None, held: bool = False, cfl: float = SimSettings.cfl,
             held_edges: Sequence[str] = ()) -> list[str]:
    """Plain sentences: the mass and material, a run long for its material's step (``steps_line``), the
    separate pieces that nothing holds up, then what each load will roughly do (a push on one of several pieces:
    on that piece). ``held``: the frame's edges ``held_edges`` hold the object (``support``)."""
    m = facts.total_mass
    g = float(np.linalg.norm(conditions.gravity()))
    ground = conditions.ground()
    lines = [f"object: {material.name}, {_fmt_mass(m)} ({len(facts.x)} particles); E = {material.E:.3g} Pa, "
             f"density {material.density:.4g} kg/m³."]
    long_run = steps_line(material, facts, clip_s, cfl, conditions)
    if long_run:
        lines.append(long_run)
    if m <= 0:
        return lines
    # Standing on the ground only: a body held at the frame's edge or by an anchor hangs from it, which the
    # column that buckles from the ground up does not describe.
    # A body the frame's bottom edge alone holds is the same column clamped at its base: it cannot tip, but it can
    # fold over or sway under its own weight.
    standing = ground is not None and not held and not conditions.of(Anchor)
    on_base = held and tuple(held_edges) == ("bottom",) and len(conditions.of(Anchor)) <= 1
    tilted = balance_line(facts, camera) if standing and facts.single else ""
    for extra in (thin_line(facts), flow_line(material, facts, g), tilted,
                  stand_line(material, facts, g, held=on_base) if (standing or on_base) and not tilted else ""):
        if extra:
            lines.append(extra)
    parts = pieces(facts, conditions, camera) if facts.dx > 0 and facts.single else []
    if len(parts) > 1:
        loose = [p for p in parts if not p.supported]
        lines.append(f"pieces: the object is {len(parts)} separate pieces (nothing binds them; the largest holds "
                     f"{parts[0].share:.0%} of the mass)" + (":" if loose else "; each is held or stands on something."))
        for p in loose[:3]:
            lines.append(f"a piece of {_fmt_mass(p.mass)} ({p.share:.0%} of the mass){_where(p.sel, facts, camera)} is "
                         "neither held nor standing on anything: it falls from the first frame (onto what is under it, or out "
                         "of the picture). If it belongs to the "
                         "object, make the mask join it to the rest (a box or a point on what joins them, or your own "
                         "mask); if not, leave it out (a background point on it).")
        if len(loose) > 3:
            rest = loose[3:]
            lines.append(f"... and {len(rest)} more such pieces ({sum(p.share for p in rest):.0%} of the mass).")
    users_anchor = bool(conditions.of(Anchor))
    anchored = held or users_anchor
    room = frame_room(facts, camera)
    for k, f in enumerate(conditions.of(Force), 1):
        t0, t1 = _window(f, clip_s)
        dt = t1 - t0
        F = np.asarray(f.vector, np.float64)
        fmag = float(np.linalg.norm(F))
        body, anch, on_ground, what = facts, anchored, ground, ""
        if len(parts) > 1:
            sel = _region_sel(f, facts, camera)
            touched = [p for p in parts if (sel & p.sel).any()]
            if touched and len(touched) < len(parts):
                tsel = np.any([p.sel for p in touched], axis=0)
                body = BodyFacts(facts.x[tsel], facts.mass[tsel], facts.dx)
                if users_anchor:
                    anch = any(p.held for p in touched)
                if not any(p.grounded for p in touched):
                    on_ground = None
                share = sum(p.share for p in touched)
                what = f" (the {'piece' if len(touched) == 1 else 'pieces'} it pushes, {share:.0%} of the object)"
                if not any(p.supported for p in touched):
                    what += "; nothing holds that piece up, so it also falls"
        lines.append(_push_line(k, F, fmag, dt, body, g, on_ground, anch, camera, clip_s, t1, f, what,
                                material, tilted=bool(tilted) and body is facts,
                                clamped=held and "bottom" in tuple(held_edges) and body is facts))
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
        line += _throw_travel(v, facts, camera, ground, g, clip_s, anchored,
                              rolls=material.model == "rigid" and rolls_along(facts, v))
        lines.append(line + ".")
    return lines


#: A solid ball pushed through its centre rolls off with this share of the speed the push would give it sliding
#: freely (m·a = F - f, I·α = f·R, a = α·R, I = 2/5·m·R²: a = 5/7·F/m), and friction carries the share 2/7 of the
#: push: past μ·m·g / (2/7) it skids as well (``_push_line``).
ROLL_SPEED_SHARE = 5.0 / 7.0
ROLL_FRICTION_SHARE = 2.0 / 7.0
#: A body rolls along a direction when its outline in the plane of that direction and the vertical is a circle
#: about its centre of mass: its largest radius in each of ROLL_BINS directions within ROLL_ROUND of their mean.
ROLL_BINS = 16
ROLL_ROUND = 0.12


def rolls_along(facts: BodyFacts, v: np.ndarray) -> bool:
    """Whether the body is round about the horizontal axis across ``v`` (a ball, a wheel seen face-on): its
    particles' largest distance from the centre of mass, in the plane of v's horizontal part and the vertical,
    the same in every direction within ROLL_ROUND (a cup or a block is not)."""
    h = np.array([float(v[0]), 0.0, float(v[2])])
    if float(np.linalg.norm(h)) <= 0 or len(facts.x) < 8 * ROLL_BINS:
        return False
    h = h / np.linalg.norm(h)
    r = facts.x.astype(np.float64) - facts.com
    a, b = r @ h, r[:, 1]
    ang = np.floor((np.arctan2(b, a) + np.pi) / (2 * np.pi) * ROLL_BINS).astype(np.int64) % ROLL_BINS
    rad = np.hypot(a, b)
    top = np.zeros(ROLL_BINS)
    np.maximum.at(top, ang, rad)
    return bool(top.min() > 0 and (top.max() - top.min()) <= ROLL_ROUND * top.mean())


def _throw_travel(v: np.ndarray, facts: BodyFacts, camera: Optional[Camera], ground: Optional[Ground], g: float,
                  clip_s: float, anchored: bool, rolls: bool = False) -> str:
    """Whether a throw takes the object out of the frame: up, to its apex v_y²/2g, and sideways, in the air
    for the flight time 2·v_y/g (landing where it started) and then sliding v_x²/2μg on a friction ground
    (for the clip's length at most; no ground or a slip one: v_x for the whole clip). A body that ``rolls``
    (``rolls_along``) is not stopped by friction: it rolls on at 5/7 of v_x (a ball) for the rest of the clip.
    Spin and bounces are left out: a rough answer, for a throw that is far too fast."""
    room = frame_room(facts, camera, top=True)
    if room is None or anchored:
        return ""
    vx, vy = abs(float(v[0])), float(v[1])
    notes = []
    if vy > 0 and g > 0 and vy * vy / (2 * g) > room[2]:
        notes.append(f"it rises about {vy * vy / (2 * g):.2g} m, past the frame's top ({room[2]:.2g} m of room)")
    if vx > 0:
        if ground is None or ground.contact == "slip" or g <= 0:
            travel = vx * clip_s
        else:
            flight = min(clip_s, 2 * vy / g) if vy > 0 else 0.0
            travel = vx * flight
            if flight < clip_s and rolls and ground.contact != "slip":
                travel += ROLL_SPEED_SHARE * vx * (clip_s - flight)  # it rolls on: friction does not stop it
            elif flight < clip_s and ground.contact != "sticky" and float(ground.friction) > 0:
                travel += min(vx * (clip_s - flight), vx * vx / (2 * float(ground.friction) * g))
        side = room[1] if v[0] > 0 else room[0]
        if travel > side:
            notes.append(f"it {'rolls' if rolls else 'travels'} about {travel:.2g} m sideways against {side:.2g} m "
                         f"of room on the {'right' if v[0] > 0 else 'left'}")
    return ("; it may leave the frame: " + " and ".join(notes) + " (a slower throw keeps it in)") if notes else ""


@dataclass
class MotionReport:
    """What the clip shows: the largest motion in pixels of the input view, the first frame where most
    of the object was outside the frame (None if never), and the warnings for the user."""

    max_motion_px: float
    left_frame_at: Optional[int]
    warnings: list
    back_in_frame_at: Optional[int] = None  # the first frame after ``left_frame_at`` with most of it inside again


def after_run(sim, camera: Camera) -> MotionReport:
    """Warn when nothing moved visibly (largest particle motion under ``STILL_PX`` in the input view,
    frames 1..end against frame 0) and when the object left the frame (``LEFT_FRACTION`` of its
    particles project outside the image or behind the camera), or, the object being in separate pieces
    (``sim.particle_piece``), when a piece of at least ``PIECE_MIN_SHARE`` of it did."""
    x = sim.x
    T = int(x.shape[0])
    uv0, _ = camera.project(x[0].float())
    motion = 0.0
    left_at = back_at = None
    W, H = float(camera.width), float(camera.height)
    piece = getattr(sim, "particle_piece", None)
    piece = None if piece is None else piece.long()
    n_pieces = int(piece.max()) + 1 if piece is not None and piece.numel() else 0
    counts = torch.bincount(piece, minlength=n_pieces).float() if n_pieces > 1 else None
    big = [] if counts is None else [p for p in range(n_pieces) if counts[p] >= PIECE_MIN_SHARE * piece.numel()]
    piece_left: dict = {}
    for k in range(1, T):
        uv, z = camera.project(x[k].float())
        motion = max(motion, float((uv - uv0).norm(dim=1).max()) if uv.shape[0] else 0.0)
        outside = (z <= 0) | (uv[:, 0] < 0) | (uv[:, 0] > W) | (uv[:, 1] < 0) | (uv[:, 1] > H)
        out = bool(uv.shape[0]) and float(outside.float().mean()) >= LEFT_FRACTION
        if left_at is None and out:
            left_at = k
        elif left_at is not None and back_at is None and not out:
            back_at = k
        if big:
            share_out = torch.bincount(piece, weights=outside.float(), minlength=n_pieces) / counts
            for p in big:
                if p not in piece_left and float(share_out[p]) >= LEFT_FRACTION:
                    piece_left[p] = k
    warnings = []
    if T > 1 and motion < STILL_PX:
        warnings.append(f"nothing moved visibly: the largest motion in the video is {motion:.2g} px. The push is too "
                        "weak for this mass and friction (see the forecast above), or the object is held; push "
                        "harder, push longer, lower the friction or the density.")
    if left_at is not None:
        back = ("it is back in from frame {} ({:.2g} s)".format(back_at, float(sim.times[back_at]))
                if back_at is not None else "it does not come back")
        warnings.append(f"the object left the frame: from frame {left_at} ({float(sim.times[left_at]):.2g} s) most "
                        f"of it is outside the picture; {back}. Use a smaller force, a shorter push, a slower "
                        "throw, more friction or fewer frames.")
    else:
        for p, k in sorted(piece_left.items(), key=lambda pk: pk[1]):
            share = float(counts[p]) / piece.numel()
            warnings.append(f"a separate piece of the object (about {share:.0%} of it) left the frame from frame {k} "
                            f"({float(sim.times[k]):.2g} s). The mask is in pieces that nothing binds together: join "
                            "them in the mask (or leave that piece out), or push less.")
    return MotionReport(motion, left_at, warnings, back_at)
