"""Physical conditions: what happens to the object (forces, torques, throws, anchors, ground, walls, gravity)
and the regions they act on. Vectors are in world coordinates (metres, newtons, +y up)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterable, Iterator, Optional, Union

import numpy as np

from ..errors import InputError
from ._checks import Vec3, as_vec3

@dataclass(frozen=True)
class Region:
    """Which part of the object a condition acts on.

    kind:
      - "all": every particle (of ``object_id`` if set).
      - "box": axis-aligned box ``lo``..``hi`` (metres, world).
      - "sphere": ``center``, ``radius`` (metres, world).
      - "image": particles whose projection in the input camera lies within ``radius_px`` of any of
        ``points`` (pixel coordinates u, v in the input image), through the whole depth; or inside
        ``mask`` (H, W) when given.
    """

    kind: str = "all"
    lo: Optional[Vec3] = None
    hi: Optional[Vec3] = None
    center: Optional[Vec3] = None
    radius: float = 0.0
    points: tuple[tuple[float, float], ...] = ()
    radius_px: float = 20.0
    mask: Optional[np.ndarray] = field(default=None, compare=False, hash=False)
    object_id: Optional[int] = None

    def __post_init__(self) -> None:
        kinds = ("all", "box", "sphere", "image")
        if self.kind not in kinds:
            raise InputError(f"Region kind must be one of {kinds}; got '{self.kind}'")
        if self.kind == "box":
            if self.lo is None or self.hi is None:
                raise InputError("A box region needs lo=(x,y,z) and hi=(x,y,z)")
            lo, hi = as_vec3(self.lo, "box lo"), as_vec3(self.hi, "box hi")
            if any(a >= b for a, b in zip(lo, hi)):
                raise InputError(f"Box region: every lo must be below hi; got lo={lo}, hi={hi}")
        if self.kind == "sphere":
            if self.center is None:
                raise InputError("A sphere region needs center=(x,y,z)")
            as_vec3(self.center, "sphere center")
            if not (math.isfinite(self.radius) and self.radius > 0):
                raise InputError(f"Sphere region radius must be positive metres; got {self.radius}")
        if self.kind == "image":
            if not self.points and self.mask is None:
                raise InputError("An image region needs points=[(u, v), ...] in pixels or a mask")
            if not (math.isfinite(self.radius_px) and self.radius_px > 0):
                raise InputError(f"Image region radius_px must be positive; got {self.radius_px}")

    @classmethod
    def whole(cls, object_id: Optional[int] = None) -> "Region":
        return cls(kind="all", object_id=object_id)

    @classmethod
    def at_pixel(cls, u: float, v: float, radius_px: float = 20.0) -> "Region":
        return cls(kind="image", points=((float(u), float(v)),), radius_px=float(radius_px))


@dataclass(frozen=True)
class _Load:
    """A vector load on a region over a time window (the fields Force and Torque share)."""

    vector: Vec3
    region: Region = field(default_factory=Region)
    t_start: float = 0.0
    t_end: float = float("inf")

    def __post_init__(self) -> None:
        name = type(self).__name__
        object.__setattr__(self, "vector", as_vec3(self.vector, f"{name} vector"))
        _check_window(self.t_start, self.t_end, name)


@dataclass(frozen=True)
class Force(_Load):
    """A total force (N) spread over the region's particles in proportion to their mass."""


@dataclass(frozen=True)
class Torque(_Load):
    """A torque (N·m) about the region's centre of mass: net force zero, net torque exact."""


@dataclass(frozen=True)
class InitialVelocity:
    """Initial linear velocity v (m/s) and angular velocity ω (rad/s, about the region's centre of mass)."""

    velocity: Vec3 = (0.0, 0.0, 0.0)
    angular_velocity: Vec3 = (0.0, 0.0, 0.0)
    region: Region = field(default_factory=Region)

    def __post_init__(self) -> None:
        object.__setattr__(self, "velocity", as_vec3(self.velocity, "InitialVelocity velocity"))
        object.__setattr__(self, "angular_velocity",
                           as_vec3(self.angular_velocity, "InitialVelocity angular_velocity"))


@dataclass(frozen=True)
class Anchor:
    """Particles of the region are held (a clamp, a hand): fixed, or moved at a prescribed
    ``velocity`` (m/s) from ``t_start`` to ``t_end``; outside that window they move freely."""

    region: Region = field(default_factory=Region)
    velocity: Vec3 = (0.0, 0.0, 0.0)
    t_start: float = 0.0
    t_end: float = float("inf")
    optional: bool = False  # a hold the run chose itself (support.py): holding nothing is skipped, not an error

    def __post_init__(self) -> None:
        object.__setattr__(self, "velocity", as_vec3(self.velocity, "Anchor velocity"))
        _check_window(self.t_start, self.t_end, "Anchor")


CONTACTS = ("sticky", "slip", "friction")


@dataclass(frozen=True)
class Ground:
    """A horizontal ground plane y = height. contact: sticky, slip, or Coulomb friction μ."""

    height: float = 0.0
    contact: str = "friction"
    friction: float = 0.5

    def __post_init__(self) -> None:
        if self.contact not in CONTACTS:
            raise InputError(f"Ground contact must be one of {CONTACTS}; got '{self.contact}'")
        if not math.isfinite(self.height):
            raise InputError(f"Ground height must be finite; got {self.height}")
        if not (math.isfinite(self.friction) and self.friction >= 0):
            raise InputError(f"Ground friction μ must be a non-negative number; got {self.friction}")


@dataclass(frozen=True)
class Walls:
    """The simulation box's side and top walls (the domain boundary). contact as for Ground."""

    contact: str = "slip"
    friction: float = 0.0

    def __post_init__(self) -> None:
        if self.contact not in CONTACTS:
            raise InputError(f"Walls contact must be one of {CONTACTS}; got '{self.contact}'")
        if not (math.isfinite(self.friction) and self.friction >= 0):
            raise InputError(f"Walls friction μ must be a non-negative number; got {self.friction}")


OBJECT_CONTACTS = ("friction", "slip", "sticky", "shared")


@dataclass(frozen=True)
class ObjectContact:
    """How objects of a scene meet (objects: ``Gaussians.object_ids``). Each object moves on its own
    grid velocity field; where two objects' fields meet and approach each other, their relative
    normal velocity is removed (multi-field MPM contact, Bardenhagen et al. 2000) and the tangential
    one follows ``contact``: Coulomb ``friction`` μ, ``slip`` (frictionless) or ``sticky`` (no
    sliding while they press together); objects may always separate again. ``shared``: one velocity
    field for all objects (the objects glue where they touch and never separate)."""

    contact: str = "friction"
    friction: float = 0.3

    def __post_init__(self) -> None:
        if self.contact not in OBJECT_CONTACTS:
            raise InputError(f"Object contact must be one of {OBJECT_CONTACTS}; got '{self.contact}'")
        if not (math.isfinite(self.friction) and self.friction >= 0):
            raise InputError(f"Object contact friction μ must be a non-negative number; got {self.friction}")


@dataclass(frozen=True)
class Gravity:
    vector: Vec3 = (0.0, -9.81, 0.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "vector", as_vec3(self.vector, "Gravity vector"))


Condition = Union[Force, Torque, InitialVelocity, Anchor, Ground, Walls, ObjectContact, Gravity]
CONDITION_TYPES = (Force, Torque, InitialVelocity, Anchor, Ground, Walls, ObjectContact, Gravity)


def _check_window(t0: float, t1: float, what: str) -> None:
    if math.isnan(t0) or math.isnan(t1) or t0 < 0 or t1 <= t0:
        raise InputError(f"{what}: the time window must satisfy 0 <= t_start < t_end; got "
                         f"t_start={t0}, t_end={t1}")


class Conditions:
    """An ordered collection of physical conditions (what flows on a PM_CONDITIONS link)."""

    def __init__(self, items: Iterable[Condition] = ()):
        items = tuple(items)
        for c in items:
            if not isinstance(c, CONDITION_TYPES):
                raise InputError(f"Not a physical condition: {c!r}")
        self.items: tuple[Condition, ...] = items

    def __iter__(self) -> Iterator[Condition]:
        return iter(self.items)

    def __len__(self) -> int:
        return len(self.items)

    def __add__(self, other) -> "Conditions":
        if isinstance(other, Conditions):
            return Conditions(self.items + other.items)
        if isinstance(other, CONDITION_TYPES):
            return Conditions(self.items + (other,))
        return Conditions(self.items + tuple(other))

    def __repr__(self) -> str:
        return f"Conditions({list(self.items)!r})"

    def of(self, kind) -> list:
        return [c for c in self.items if isinstance(c, kind)]

    def gravity(self) -> Vec3:
        g = self.of(Gravity)
        if len(g) > 1:
            raise InputError("Only one Gravity condition may be given; remove the extra ones")
        return g[0].vector if g else Gravity().vector

    def ground(self) -> Optional[Ground]:
        g = self.of(Ground)
        if len(g) > 1:
            raise InputError("Only one Ground condition may be given; remove the extra ones")
        return g[0] if g else None

    def walls(self) -> Walls:
        w = self.of(Walls)
        if len(w) > 1:
            raise InputError("Only one Walls condition may be given; remove the extra ones")
        return w[0] if w else Walls()

    def object_contact(self) -> ObjectContact:
        c = self.of(ObjectContact)
        if len(c) > 1:
            raise InputError("Only one ObjectContact condition may be given; remove the extra ones")
        return c[0] if c else ObjectContact()
