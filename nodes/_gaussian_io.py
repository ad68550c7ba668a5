"""Splat inputs that take our PM_GAUSSIANS or ComfyUI's native splats (``SPLAT``, formerly ``GAUSSIAN``).

Use ``GAUSSIANS_INPUT`` as the input type and ``as_pm_gaussians(value)`` in the run function::

    "gaussians": (GAUSSIANS_INPUT, {"tooltip": "..." + GAUSSIANS_TOOLTIP_SUFFIX})
    ...                                                   # optional, where a splat enters:
    "splat_axes": SPLAT_AXES_INPUT,
    ...
    g = as_pm_gaussians(gaussians, axes=splat_axes)

A union of link types is one comma-separated string without spaces: ComfyUI's back end
(``comfy_execution/validation.py: validate_node_input``, 0.3.64) accepts a link whose type is any one
of them, and the front end's ``LiteGraph.isValidConnection`` splits both sides on "," and connects
when one pair matches (it does not trim spaces, hence none). Both native names are always listed:
upstream named the type ``GAUSSIAN`` (PR #14190) and later ``SPLAT``; a ComfyUI with either (or neither)
connects what it has, and a workflow saved on one version loads on the other.

Batch meaning, as upstream's: each item of a native batch is an independent splat (TripoSplat decodes one
per input image, Render Splat renders each). These inputs take one scene, so they take one item and
refuse a batch of several with what to do (the converter node makes each item an object); a batch that
is the frames of a simulation fed back is named as such. Axes: the native frame is y down (3DGS); the
default ``y_down`` turns it 180° about x into ours (+y up); ``as_is`` copies x y z.
"""

from __future__ import annotations

import logging
from typing import Any, Optional

from physmotion_core.errors import InputError

log = logging.getLogger("physmotion.nodes")

#: Every name upstream has given the native splat type, newest first (io_type strings).
NATIVE_SPLAT_NAMES = ("SPLAT", "GAUSSIAN")


def _detect_native() -> tuple[Optional[type], Optional[str]]:
    """(class, link type) of the running ComfyUI's native splats: comfy_api.latest ``Types.SPLAT`` with
    ``IO.Splat`` (the newer upstream name), else ``Types.GAUSSIAN`` with ``IO.Gaussian`` (upstream since
    PR #14190). (None, None) outside ComfyUI or on one without the type (0.3.64)."""
    try:
        from comfy_api.latest import Types  # noqa: PLC0415 - only inside ComfyUI
    except Exception:  # noqa: BLE001 - no comfy_api, or one that fails to import here
        return None, None
    try:
        from comfy_api.latest import IO  # 0.3.64 has no IO alias (and no splat type)
    except Exception:  # noqa: BLE001
        IO = None
    for cls_name, io_name in (("SPLAT", "Splat"), ("GAUSSIAN", "Gaussian")):
        cls = getattr(Types, cls_name, None)
        if cls is not None:
            io_type = getattr(getattr(IO, io_name, None), "io_type", None) or cls_name
            return cls, str(io_type)
    return None, None


_NATIVE_CLS, _NATIVE_TYPE = _detect_native()
#: The link type the pack's native outputs carry on the running ComfyUI: what it defines (SPLAT on a current
#: one, GAUSSIAN on one from the GAUSSIAN era); "SPLAT" where there is none (the converters are not
#: registered then, so nothing outputs it).
NATIVE_GAUSSIAN_TYPE = _NATIVE_TYPE or NATIVE_SPLAT_NAMES[0]
#: The input type of every node input that takes Gaussians: ours and every native name.
GAUSSIANS_INPUT = ",".join(dict.fromkeys(("PM_GAUSSIANS",) + NATIVE_SPLAT_NAMES + ((_NATIVE_TYPE,) if _NATIVE_TYPE else ())))
#: Say this in the tooltip of such an input.
GAUSSIANS_TOOLTIP_SUFFIX = (" Also takes ComfyUI's native SPLAT (GAUSSIAN on older versions: TripoSplat, Get Splat / "
                            "3D File to Gaussian Splat): one item of the batch, one scene, turned from its y-down "
                            "frame into ours (+y up) unless splat_axes says as_is.")

SPLAT_AXES = ["y_down", "as_is"]
SPLAT_AXES_TOOLTIP = ("Only for a native SPLAT/GAUSSIAN on the splat input. y_down: the native frame (ComfyUI's splat "
                      "nodes, 3DGS files and the .ply files PhysMotion writes: y down, z away from the camera), "
                      "turned 180° about x into ours (+y up; exact). as_is: copy x y z unchanged (a splat already "
                      "+y up, e.g. a .ply PhysMotion wrote before it recorded its axes).")
#: The optional input that offers the choice where a splat enters: ``"splat_axes": SPLAT_AXES_INPUT``.
SPLAT_AXES_INPUT = (SPLAT_AXES, {"default": "y_down", "tooltip": SPLAT_AXES_TOOLTIP})


def as_pm_gaussians(value: Any, name: str = "gaussians", axes: str = "y_down"):
    """Our Gaussians from a PM_GAUSSIANS or a native splat value (one item: upstream's batch meaning;
    clear error otherwise)."""
    from physmotion_core.interop_gaussian import from_native_one, is_native_gaussian
    from physmotion_core.types.gaussians import Gaussians

    if isinstance(value, Gaussians):
        return value
    if is_native_gaussian(value):
        return from_native_one(value, axes=axes, where=name).to("cpu")  # links carry CPU Gaussians
    raise InputError(f"{name}: expected PM_GAUSSIANS or a native SPLAT/GAUSSIAN, got {type(value).__name__}. "
                     "Connect a lift node, Load Gaussians, or one of ComfyUI's splat nodes.")


def native_gaussian_class() -> Optional[type]:
    """The running ComfyUI's native splat class (comfy_api.latest Types.SPLAT, or Types.GAUSSIAN on a
    version from before the rename), or None when it has neither (e.g. 0.3.64) or outside ComfyUI."""
    return _NATIVE_CLS
