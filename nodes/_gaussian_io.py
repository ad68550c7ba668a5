"""Gaussian inputs that take either our PM_GAUSSIANS or ComfyUI's native GAUSSIAN.

Use ``GAUSSIANS_INPUT`` as the input type and ``as_pm_gaussians(value)`` in the run function::

    "gaussians": (GAUSSIANS_INPUT, {"tooltip": "..."})
    ...
    g = as_pm_gaussians(gaussians)

A union of link types is one comma-separated string without spaces: ComfyUI's back end
(``comfy_execution/validation.py: validate_node_input``, 0.3.64) accepts a link whose type is any one
of them, and the front end's ``LiteGraph.isValidConnection`` splits both sides on "," and connects
when one pair matches (it does not trim spaces, hence none). On a ComfyUI without the native type
the GAUSSIAN half simply never matches anything.

A native GAUSSIAN becomes one scene: one batch item is one object (several items: object_ids 0, 1, ...
in batch order, as Combine Objects numbers them), with its axes turned from the native y-down frame
into ours (see physmotion_core.interop_gaussian).
"""

from __future__ import annotations

import logging
from typing import Any, Optional

from physmotion_core.errors import InputError

log = logging.getLogger("physmotion.nodes")


def _detect_native() -> tuple[Optional[type], str]:
    """(class, link type) of the running ComfyUI's native splats: comfy_api.latest ``Types.GAUSSIAN`` with
    ``IO.Gaussian`` (upstream since PR #14190; a later upstream commit names the class ``SPLAT``, so that
    spelling is accepted too). (None, "GAUSSIAN") outside ComfyUI or on one without the type (0.3.64)."""
    try:
        from comfy_api.latest import Types  # noqa: PLC0415 - only inside ComfyUI
    except Exception:  # noqa: BLE001 - no comfy_api, or one that fails to import here
        return None, "GAUSSIAN"
    try:
        from comfy_api.latest import IO  # 0.3.64 has no IO alias (and no GAUSSIAN)
    except Exception:  # noqa: BLE001
        IO = None
    for cls_name, io_name in (("GAUSSIAN", "Gaussian"), ("SPLAT", "Splat")):
        cls = getattr(Types, cls_name, None)
        if cls is not None:
            io_type = getattr(getattr(IO, io_name, None), "io_type", None) or "GAUSSIAN"
            return cls, str(io_type)
    return None, "GAUSSIAN"


_NATIVE_CLS, NATIVE_GAUSSIAN_TYPE = _detect_native()
#: The input type of every node input that takes Gaussians ("PM_GAUSSIANS,GAUSSIAN").
GAUSSIANS_INPUT = "PM_GAUSSIANS," + NATIVE_GAUSSIAN_TYPE
#: Say this in the tooltip of such an input.
GAUSSIANS_TOOLTIP_SUFFIX = (" Also takes ComfyUI's native GAUSSIAN (TripoSplat, 3D File to Gaussian Splat): "
                            "each batch item is one object, turned from its y-down frame into ours (+y up).")


def as_pm_gaussians(value: Any, name: str = "gaussians"):
    """Our Gaussians from a PM_GAUSSIANS or a native GAUSSIAN value (clear error otherwise)."""
    from physmotion_core.interop_gaussian import from_native_scene, is_native_gaussian
    from physmotion_core.types.gaussians import Gaussians

    if isinstance(value, Gaussians):
        return value
    if is_native_gaussian(value):
        return from_native_scene(value, axes="y_down").to("cpu")  # links carry CPU Gaussians
    raise InputError(f"{name}: expected PM_GAUSSIANS or a native GAUSSIAN, got {type(value).__name__}. "
                     "Connect a lift node, Load Gaussians, or one of ComfyUI's Gaussian nodes.")


def native_gaussian_class() -> Optional[type]:
    """The running ComfyUI's native splat class (comfy_api.latest Types.GAUSSIAN), or None when this
    ComfyUI has no such type (e.g. 0.3.64) or runs outside ComfyUI."""
    return _NATIVE_CLS
