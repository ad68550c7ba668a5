"""Converters between PhysMotion's Gaussians and ComfyUI's native splats (``SPLAT``; ``GAUSSIAN`` before
upstream renamed it).

Registered only when the running ComfyUI has the type (comfy_api.latest Types.SPLAT, or Types.GAUSSIAN on a
version from before the rename); on older ComfyUI (e.g. 0.3.64) this module has no nodes and says so in one
log line. Their outputs carry the link type the running ComfyUI defines, their inputs take both names. The
node ids keep the GAUSSIAN spelling so saved workflows load. The conversions live in
physmotion_core.interop_gaussian.
"""

from __future__ import annotations

from ._gaussian_io import (NATIVE_GAUSSIAN_TYPE, NATIVE_SPLAT_NAMES, SPLAT_AXES_TOOLTIP, as_pm_gaussians, log,
                           native_gaussian_class)
from ._util import CATEGORY, progress_callback

AXES_CHOICES = ["y_down", "as_is"]
AXES_TOOLTIP = SPLAT_AXES_TOOLTIP
#: The native input: both upstream names (and the running one's), comma-joined as a union.
NATIVE_INPUT = ",".join(dict.fromkeys(NATIVE_SPLAT_NAMES + (NATIVE_GAUSSIAN_TYPE,)))

_NATIVE_CLS = native_gaussian_class()


class PhysMotionFromGAUSSIAN:
    """ComfyUI GAUSSIAN -> PM_GAUSSIANS."""

    DESCRIPTION = ("Turns ComfyUI's native SPLAT (GAUSSIAN on older versions: TripoSplat, Get Splat, ...) into "
                   "PhysMotion Gaussians: each batch item (an independent splat) becomes one object of the scene "
                   "(object ids 0, 1, ...). A batch of simulated frames fed back is refused: its items are one "
                   "object at different times, not objects.")

    @classmethod
    def INPUT_TYPES(cls):
        return {"required": {
            "gaussian": (NATIVE_INPUT, {"tooltip": "ComfyUI's SPLAT (or GAUSSIAN) splats; each batch item becomes "
                                                   "one object."}),
            "axes": (AXES_CHOICES, {"default": "y_down", "tooltip": AXES_TOOLTIP}),
        }}

    RETURN_TYPES = ("PM_GAUSSIANS",)
    RETURN_NAMES = ("gaussians",)
    OUTPUT_TOOLTIPS = ("The splats as PhysMotion Gaussians (metres as stored; +y up with axes=y_down).",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/io"

    def run(self, gaussian, axes):
        from physmotion_core.interop_gaussian import from_native_scene, is_native_gaussian

        if not is_native_gaussian(gaussian):
            return (as_pm_gaussians(gaussian, "gaussian"),)  # clear error, or our own Gaussians passed through
        return (from_native_scene(gaussian, axes=axes).to("cpu"),)  # links carry CPU Gaussians


class PhysMotionToGAUSSIAN:
    """PM_GAUSSIANS -> ComfyUI GAUSSIAN."""

    DESCRIPTION = ("Turns PhysMotion Gaussians into ComfyUI's native SPLAT (GAUSSIAN on older versions), for Render "
                   "Splat, Create 3D File (from Splat), Merge/Transform Splat and the splat preview.")

    @classmethod
    def INPUT_TYPES(cls):
        return {"required": {
            "gaussians": ("PM_GAUSSIANS", {"tooltip": "PhysMotion Gaussians (a lift, Fit, Refine or Combine Objects)."}),
            "axes": (AXES_CHOICES, {"default": "y_down", "tooltip": AXES_TOOLTIP}),
            "split_objects": ("BOOLEAN", {"default": False,
                                          "tooltip": "On: one batch item per object of a combined scene. Off: the "
                                                     "whole scene as one item (what Render and Save expect)."}),
        }}

    RETURN_TYPES = (NATIVE_GAUSSIAN_TYPE,)
    RETURN_NAMES = ("gaussian",)
    OUTPUT_TOOLTIPS = ("The Gaussians as ComfyUI's SPLAT/GAUSSIAN (linear scales, wxyz, opacities in [0, 1], SH kept): "
                       "one item, or one per object with split_objects.",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/io"

    def run(self, gaussians, axes, split_objects):
        from physmotion_core.interop_gaussian import to_native

        g = as_pm_gaussians(gaussians).detach()
        return (to_native(g, _NATIVE_CLS, axes=axes, split=bool(split_objects)),)


class PhysMotionSimToGAUSSIAN:
    """PM_SIM -> a GAUSSIAN batch, one item per simulated frame."""

    DESCRIPTION = ("The simulated Gaussians of every frame as one native SPLAT/GAUSSIAN batch (item k = frame k, "
                   "shaped exactly as PhysMotion Render draws it), for Render Splat (one image per item), Create 3D "
                   "File (from Splat) and the splat preview. The batch is marked as frames: PhysMotion inputs refuse "
                   "it as objects.")

    @classmethod
    def INPUT_TYPES(cls):
        return {"required": {
            "simulation": ("PM_SIM", {"tooltip": "The simulated trajectory (from MPM Simulate)."}),
            "every_nth_frame": ("INT", {"default": 1, "min": 1, "max": 1000,
                                        "tooltip": "Keep every n-th frame (1 = all; frame 0 is always kept)."}),
            "axes": (AXES_CHOICES, {"default": "y_down", "tooltip": AXES_TOOLTIP}),
        }}

    RETURN_TYPES = (NATIVE_GAUSSIAN_TYPE,)
    RETURN_NAMES = ("gaussian",)
    OUTPUT_TOOLTIPS = ("One batch item per kept frame; deformed shapes as rotation + scales.",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/io"

    def run(self, simulation, every_nth_frame, axes):
        from physmotion_core.interop_gaussian import sim_to_native_tensors

        t = sim_to_native_tensors(simulation, axes=axes, every=int(every_nth_frame), progress=progress_callback())
        out = _NATIVE_CLS(t["positions"], t["scales"], t["rotations"], t["opacities"], t["sh"], counts=t["counts"])
        out.physmotion_frame_batch = True  # read by interop_gaussian.frame_batch_reason
        return (out,)


if _NATIVE_CLS is None:
    log.info("PhysMotion: this ComfyUI has no native splat type (SPLAT or GAUSSIAN); the splat converter nodes are "
             "not registered (PhysMotion nodes still take PM_GAUSSIANS)")
    NODE_CLASS_MAPPINGS: dict = {}
    NODE_DISPLAY_NAME_MAPPINGS: dict = {}
else:
    NODE_CLASS_MAPPINGS = {
        "PhysMotionFromGAUSSIAN": PhysMotionFromGAUSSIAN,
        "PhysMotionToGAUSSIAN": PhysMotionToGAUSSIAN,
        "PhysMotionSimToGAUSSIAN": PhysMotionSimToGAUSSIAN,
    }
    NODE_DISPLAY_NAME_MAPPINGS = {
        "PhysMotionFromGAUSSIAN": f"PhysMotion {NATIVE_GAUSSIAN_TYPE} to PhysMotion Gaussians",
        "PhysMotionToGAUSSIAN": f"PhysMotion Gaussians to {NATIVE_GAUSSIAN_TYPE}",
        "PhysMotionSimToGAUSSIAN": f"PhysMotion Simulation to {NATIVE_GAUSSIAN_TYPE} (one item per frame)",
    }
