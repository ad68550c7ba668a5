"""The data every stage passes on, one module per thing it describes.

=================  =====================================================================
``gaussians``      Gaussians (the splats), SH_C0, quaternion <-> rotation matrix
``camera``         Camera (pinhole, OpenGL pose)
``material``       Material and the constitutive models it can name
``conditions``     Region, Force, Torque, InitialVelocity, Anchor, Ground, Walls, ObjectContact,
                   Gravity, Conditions
``settings``       SimSettings (how to simulate) and its presets
``results``        SimResult (the trajectory), FrameSet (rendered frames), the splat deformation rule
=================  =====================================================================

Conventions (README.md, "Conventions"): right-handed world in metres/seconds/kilograms, +y up, gravity -y.

The library imports each name from its own module (``from physmotion_core.types.camera import Camera``).
``from physmotion_core.types import Camera`` still works for callers' code: the names are looked up
here on first use, so importing one module never loads the others.
"""

from __future__ import annotations

import importlib

_HOME = {
    "gaussians": ("SH_C0", "Gaussians", "quat_to_rotmat", "rotmat_to_quat"),
    "camera": ("Camera",),
    "material": ("CONSTITUTIVE_MODELS", "Material"),
    "conditions": ("Region", "Force", "Torque", "InitialVelocity", "Anchor", "CONTACTS", "Ground", "Walls",
                   "OBJECT_CONTACTS", "ObjectContact", "Gravity", "CONDITION_TYPES", "Conditions"),
    "settings": ("AUTO_GRID_RES", "QUALITY", "MAX_CFL", "SimSettings"),
    "results": ("MAX_SPLAT_STRETCH", "splat_deformation", "SimResult", "FrameSet"),
}
_MODULE_OF = {name: module for module, names in _HOME.items() for name in names}

__all__ = sorted(_MODULE_OF)


def __getattr__(name: str):
    module = _MODULE_OF.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
