"""Materials: the physical parameters (SI units) and the constitutive model each object is simulated with."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass


from ..errors import InputError

CONSTITUTIVE_MODELS = (
    "fixed_corotated", "neo_hookean", "von_mises", "drucker_prager", "snow", "plasticine",
    "fracture", "viscoplastic", "fluid", "rigid",
)


@dataclass
class Material:
    """Physical material in SI units. ``model`` selects the constitutive + return-mapping rule.

    Only the fields a model uses matter; presets (``Material.preset``) carry sensible values.
    """

    name: str = "jelly"
    model: str = "fixed_corotated"
    E: float = 2.0e4  # Young's modulus, Pa
    nu: float = 0.3  # Poisson's ratio
    density: float = 1000.0  # kg/m^3
    yield_stress: float = float("inf")  # Pa, von Mises equivalent (metal, plasticine, viscoplastic)
    hardening: float = 0.0  # Pa of yield stress gained per unit equivalent plastic strain (metal)
    softening: float = 0.0  # Pa of yield stress lost per unit equivalent plastic strain (plasticine)
    friction_angle: float = 30.0  # degrees (Drucker-Prager sand)
    cohesion: float = 0.0  # Pa of tensile mean stress the sand can carry (Drucker-Prager)
    yield_surface: str = "triaxial"  # Drucker-Prager cone matched to Mohr-Coulomb in "triaxial" compression
    #                                  (Klár et al. 2016, PhysGaussian) or in "plane_strain" (weaker; see docs/materials.md)
    viscosity: float = 0.0  # Pa*s (fluid: dynamic viscosity; viscoplastic: Perzyna plastic viscosity)
    bulk_modulus: float = 0.0  # Pa (fluid equation of state)
    gamma: float = 7.0  # fluid equation-of-state exponent (Tait)
    crit_compression: float = 2.5e-2  # snow theta_c
    crit_stretch: float = 7.5e-3  # snow theta_s
    hardening_xi: float = 10.0  # snow xi
    fracture_stretch: float = 0.0  # principal stretch beyond which the material tears (fracture model)
    damping: float = 0.0  # mass-proportional velocity damping, 1/s (0 = physical)

    @classmethod
    def preset(cls, name: str, **overrides) -> "Material":
        from ..sim.materials import material_preset  # local import: sim depends on types

        return material_preset(name, **overrides)

    @property
    def mu(self) -> float:
        return self.E / (2.0 * (1.0 + self.nu))

    @property
    def lam(self) -> float:
        return self.E * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))

    def wave_speed(self) -> float:
        """Sound speed at rest, m/s (the CFL limit uses it): sqrt((λ+2μ)/ρ), or sqrt(Kγ/ρ) for a
        fluid, 0 for a rigid body (its step is limited by its speed and acceleration only)."""
        if self.model == "rigid":
            return 0.0
        if self.model == "fluid":
            return math.sqrt(self.bulk_modulus * self.gamma / self.density)
        return math.sqrt((self.lam + 2.0 * self.mu) / self.density)

    def validate(self) -> None:
        if self.model not in CONSTITUTIVE_MODELS:
            raise InputError(f"Material '{self.name}': unknown model '{self.model}'. "
                             f"Choose one of: {', '.join(CONSTITUTIVE_MODELS)}")
        for key in dataclasses.fields(self):
            value = getattr(self, key.name)
            if isinstance(value, float) and math.isnan(value):
                raise InputError(f"Material '{self.name}': {key.name} is NaN; give a number")
        if not (math.isfinite(self.E) and self.E > 0):
            raise InputError(f"Material '{self.name}': Young's modulus E must be a finite positive "
                             f"number of pascals (jelly ~1e4, rubber ~1e6, metal ~1e10); got {self.E}")
        if not (0.0 <= self.nu < 0.5):
            raise InputError(f"Material '{self.name}': Poisson's ratio nu must be in [0, 0.5) "
                             f"(0.5 is perfectly incompressible and makes λ infinite); got {self.nu}")
        if not (math.isfinite(self.density) and self.density > 0):
            raise InputError(f"Material '{self.name}': density must be a finite positive kg/m³ value "
                             f"(water 1000, steel 7850); got {self.density}")
        if not (0.0 <= self.friction_angle < 90.0):
            raise InputError(f"Material '{self.name}': friction_angle must be in [0, 90) degrees; "
                             f"got {self.friction_angle}")
        if self.yield_surface not in ("triaxial", "plane_strain"):
            raise InputError(f"Material '{self.name}': yield_surface must be 'triaxial' or 'plane_strain'; "
                             f"got {self.yield_surface!r}")
        if not self.yield_stress > 0:
            raise InputError(f"Material '{self.name}': yield_stress must be positive Pa; got {self.yield_stress}")
        if self.model in ("von_mises", "plasticine", "viscoplastic") and not math.isfinite(self.yield_stress):
            raise InputError(f"Material '{self.name}': the {self.model} model needs a finite yield_stress in Pa "
                             "(metal ~1e5-1e8, clay ~1e4, toothpaste ~100)")
        if self.model == "fluid" and not self.bulk_modulus > 0:
            raise InputError(f"Material '{self.name}': a fluid needs bulk_modulus > 0 Pa (water preset: 2e5)")
        if self.model == "fracture" and not self.fracture_stretch > 1.0:
            raise InputError(f"Material '{self.name}': fracture_stretch must be > 1 (the principal stretch at "
                             f"which it tears, e.g. 1.1 = 10 %); got {self.fracture_stretch}")
        if self.model == "snow" and not (0 < self.crit_compression < 1 and self.crit_stretch > 0):
            raise InputError(f"Material '{self.name}': snow needs 0 < crit_compression < 1 and crit_stretch > 0")
        if not (1.0 <= self.gamma <= 20.0):
            raise InputError(f"Material '{self.name}': gamma must be in [1, 20] (water: 7); got {self.gamma}")
        for key in ("hardening", "softening", "cohesion", "viscosity", "bulk_modulus", "damping",
                    "fracture_stretch", "crit_compression", "crit_stretch", "hardening_xi"):
            v = getattr(self, key)
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"Material '{self.name}': {key} must be a finite non-negative number; got {v}")
