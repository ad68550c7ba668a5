"""Material presets in SI units and the table of constitutive models the MPM kernels implement.

Values are order-of-magnitude physical (E of gelatin desserts is 1-30 kPa, rubber ~1 MPa, steel
~200 GPa), then chosen so that each preset looks like its name at the default object size (0.3 m).
Every field is overridable: ``material_preset("jelly", E=5e4)``.
"""

from __future__ import annotations

import dataclasses

from ..errors import InputError
from ..types import Material

# name -> (constitutive model, parameters). Users see these names in the node's material list.
PRESETS: dict[str, dict] = {
    "jelly": dict(model="fixed_corotated", E=2.0e4, nu=0.3, density=1000.0),
    "rubber": dict(model="neo_hookean", E=1.0e6, nu=0.45, density=1100.0),
}

# Models the kernels implement today. A preset whose model is not listed here is refused with a
# clear message by the simulator rather than run with the wrong physics.
IMPLEMENTED_MODELS = ("fixed_corotated", "neo_hookean")

# Integer ids used inside the Warp kernels.
MODEL_IDS = {"fixed_corotated": 0, "neo_hookean": 1}


def material_names() -> list[str]:
    return list(PRESETS)


def material_preset(name: str, **overrides) -> Material:
    key = name.strip().lower()
    if key not in PRESETS:
        raise InputError(f"Unknown material '{name}'. Choose one of: {', '.join(PRESETS)} "
                         "(or build a Material with explicit parameters)")
    params = {**PRESETS[key], **{k: v for k, v in overrides.items() if v is not None}}
    fields = {f.name for f in dataclasses.fields(Material)}
    unknown = set(params) - fields
    if unknown:
        raise InputError(f"Unknown material parameter(s) {sorted(unknown)}; valid: {sorted(fields - {'name'})}")
    mat = Material(name=key, **params)
    mat.validate()
    return mat
