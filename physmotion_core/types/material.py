"""Materials, in one place: the parameters (SI units), the constitutive models a material can name (and
the id each has inside the Warp kernels), the presets and the ``key=value`` overrides users type.

Preset values are physical where the time step allows it, and otherwise keep the behaviour that defines
the material while lowering the wave speed (the CFL limit makes an explicit step proportional to
1/sqrt(E)). Where a preset departs from the real material, its note says so; every field can be
overridden, e.g. ``material_preset("metal", E=2e11)`` for real steel (same bending, ~30x more
substeps). The kernels' parameter table is built from a Material by ``sim.materials.kernel_params``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from ..errors import InputError

CONSTITUTIVE_MODELS = (
    "fixed_corotated", "neo_hookean", "von_mises", "drucker_prager", "snow", "plasticine",
    "fracture", "viscoplastic", "fluid", "rigid",
)
ELASTIC_MODELS = ("fixed_corotated", "neo_hookean")


def model_id(model: str) -> int:
    """The integer the Warp kernels know ``model`` by (``sim.constitutive.MODEL_*``): its place in CONSTITUTIVE_MODELS."""
    return CONSTITUTIVE_MODELS.index(model)


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


# name -> parameters; "note" is documentation shown in the README table, not a Material field.
PRESETS: dict[str, dict] = {
    "jelly": dict(model="fixed_corotated", E=2.0e4, nu=0.3, density=1000.0,
                  note="gelatin dessert: E 1-30 kPa"),
    "rubber": dict(model="neo_hookean", E=1.0e6, nu=0.45, density=1100.0,
                   note="soft rubber: E ~1 MPa, nearly incompressible"),
    "metal": dict(model="von_mises", E=2.0e8, nu=0.3, density=7850.0, yield_stress=3.0e5, hardening=2.0e6,
                  note="steel's density and yield strain (0.15 %), E lowered from 2e11 Pa so the step is 30x "
                       "longer: it bends and stays bent the same way"),
    "sand": dict(model="drucker_prager", E=3.5e5, nu=0.3, density=1600.0, friction_angle=32.0, cohesion=0.0,
                 note="dry sand: bulk density 1600 kg/m³, angle of repose ~32°, no tensile strength"),
    "snow": dict(model="snow", E=1.4e5, nu=0.2, density=400.0, crit_compression=2.5e-2, crit_stretch=7.5e-3,
                 hardening_xi=10.0, note="Stomakhin et al. 2013 parameters"),
    "plasticine": dict(model="plasticine", E=1.0e6, nu=0.35, density=1800.0, yield_stress=2.0e4,
                       softening=5.0e3, note="modelling clay: yields at ~20 kPa and softens as it is worked"),
    "clay": dict(model="plasticine", E=2.0e6, nu=0.4, density=1900.0, yield_stress=4.0e4, softening=2.0e3,
                 note="stiffer, wetter clay"),
    "bread": dict(model="fracture", E=5.0e4, nu=0.2, density=250.0, fracture_stretch=1.12,
                  note="soft bread: tears once stretched 12 %"),
    "cookie": dict(model="fracture", E=1.0e6, nu=0.25, density=1100.0, fracture_stretch=1.02,
                   note="brittle: breaks at 2 % stretch"),
    "toothpaste": dict(model="viscoplastic", E=5.0e4, nu=0.4, density=1300.0, yield_stress=200.0, viscosity=10.0,
                       note="Bingham-like paste: holds its shape below ~200 Pa, flows above"),
    "honey": dict(model="viscoplastic", E=1.0e4, nu=0.45, density=1400.0, yield_stress=1.0, viscosity=10.0,
                  note="viscous liquid (10 Pa·s) with a negligible yield stress"),
    "water": dict(model="fluid", E=1.0, nu=0.0, density=1000.0, bulk_modulus=2.0e5, gamma=7.0, viscosity=1.0e-3,
                  note="weakly compressible: bulk modulus lowered from 2.2e9 Pa (sound speed 37 m/s keeps the "
                       "density error under 1 % for flows below ~4 m/s)"),
    "rigid": dict(model="rigid", E=1.0e9, nu=0.3, density=1000.0,
                  note="a rigid body (E unused): its particles move with one rigid motion"),
}


def material_names() -> list[str]:
    return list(PRESETS)


def material_preset(name: str, **overrides) -> Material:
    key = str(name).strip().lower()
    if key not in PRESETS:
        raise InputError(f"Unknown material '{name}'. Choose one of: {', '.join(PRESETS)} "
                         "(or build a Material with explicit parameters)")
    params = {k: v for k, v in PRESETS[key].items() if k != "note"}
    params.update({k: v for k, v in overrides.items() if v is not None})
    fields = {f.name for f in dataclasses.fields(Material)}
    unknown = set(params) - fields
    if unknown:
        raise InputError(f"Unknown material parameter(s) {sorted(unknown)}; valid: {sorted(fields - {'name'})}")
    mat = Material(name=key, **params)
    mat.validate()
    return mat


def parse_overrides(text: str) -> dict:
    """Parse "key=value, key=value" material overrides (e.g. "yield_stress=1e5, friction_angle=35",
    "yield_surface=plane_strain")."""
    out: dict[str, object] = {}
    fields = {f.name for f in dataclasses.fields(Material)} - {"name", "model"}
    words = {"yield_surface"}  # the one override that is a word, not a number
    for item in (text or "").replace(";", ",").replace("\n", ",").split(","):
        item = item.strip()
        if not item:
            continue
        if "=" not in item:
            raise InputError(f"Material override '{item}' is not key=value (e.g. yield_stress=1e5)")
        key, value = (s.strip() for s in item.split("=", 1))
        if key not in fields:
            raise InputError(f"Unknown material parameter '{key}'; valid: {', '.join(sorted(fields))}")
        if key in words:
            out[key] = value
            continue
        try:
            out[key] = float(value)
        except ValueError:
            raise InputError(f"Material override {key}='{value}' is not a number") from None
    return out
