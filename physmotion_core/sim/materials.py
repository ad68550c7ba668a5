"""Material presets in SI units, and their translation into the kernels' parameter table.

Values are physical where the time step allows it, and otherwise keep the behaviour that defines
the material while lowering the wave speed (the CFL limit makes an explicit step proportional to
1/sqrt(E)). Where a preset departs from the real material, its note says so; every field can be
overridden, e.g. ``material_preset("metal", E=2e11)`` for real steel (same bending, ~30x more
substeps).
"""

from __future__ import annotations

import dataclasses
import math

from ..errors import InputError
from ..types import Material

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

# Integer ids used inside the Warp kernels (constitutive.MODEL_*).
MODEL_IDS = {
    "fixed_corotated": 0, "neo_hookean": 1, "von_mises": 2, "drucker_prager": 3, "snow": 4, "plasticine": 5,
    "fracture": 6, "viscoplastic": 7, "fluid": 8, "rigid": 9,
}
IMPLEMENTED_MODELS = tuple(MODEL_IDS)
ELASTIC_MODELS = ("fixed_corotated", "neo_hookean")


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


def kernel_params(mat: Material):
    """The kernels' MaterialParams struct for a validated Material."""
    from .constitutive import MaterialParams

    p = MaterialParams()
    p.model = MODEL_IDS[mat.model]
    p.mu = mat.mu
    p.lam = mat.lam
    p.density = mat.density
    p.yield_stress = mat.yield_stress if math.isfinite(mat.yield_stress) else 1.0e30
    p.hardening = mat.hardening
    p.softening = mat.softening
    s = math.sin(math.radians(mat.friction_angle))
    # The cone |dev τ| <= α (−tr τ). Matched to Mohr–Coulomb in triaxial compression (Klár et al. 2016):
    # α = √(2/3) 2 sinφ / (3 − sinφ). In plane strain with the mapping's volume-preserving flow the
    # out-of-plane deviatoric stress vanishes at yield, so √J2 = (σ1 − σ3)/2 and tr τ / 3 = (σ1 + σ3)/2,
    # and Mohr–Coulomb's (σ1 − σ3)/2 = −(σ1 + σ3)/2 · sinφ gives α = √2 sinφ / 3 (0.71× the former at 32°).
    if mat.yield_surface == "plane_strain":
        p.dp_alpha = math.sqrt(2.0) * s / 3.0
    else:
        p.dp_alpha = math.sqrt(2.0 / 3.0) * 2.0 * s / (3.0 - s)
    p.cohesion_tr = 3.0 * mat.cohesion / (3.0 * mat.lam + 2.0 * mat.mu)
    p.viscosity = mat.viscosity
    p.bulk = mat.bulk_modulus
    p.gamma = mat.gamma
    p.theta_c = mat.crit_compression
    p.theta_s = mat.crit_stretch
    p.xi = mat.hardening_xi
    p.fracture_stretch = mat.fracture_stretch if mat.fracture_stretch > 0 else 1.0e30
    p.damping = mat.damping
    return p


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
