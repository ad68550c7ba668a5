"""Converters between PhysMotion's Gaussians and ComfyUI's native GAUSSIAN splats.

Registered only when the running ComfyUI has the GAUSSIAN type (comfy_api.latest Types.GAUSSIAN,
added upstream in 2026); on older ComfyUI (e.g. 0.3.64) this module has no nodes and says so in one
log line. The conversions themselves live in physmotion_core.interop_gaussian.
"""

from __future__ import annotations

from ._gaussian_io import NATIVE_GAUSSIAN_TYPE, as_pm_gaussians, log, native_gaussian_class
from ._util import CATEGORY, progress_callback

AXES_CHOICES = ["y_down", "as_is"]
AXES_TOOLTIP = ("y_down: the native nodes' frame (their renderer looks down +z with +y pointing down the image); "
                "ours is +y up, so the scene is turned 180° about x (exact). as_is: copy x y z unchanged, as "
                ".ply files store them (use it for a GAUSSIAN read from a .ply that PhysMotion wrote).")

_NATIVE_CLS = native_gaussian_class()


class PhysMotionFromGAUSSIAN:
    """ComfyUI GAUSSIAN -> PM_GAUSSIANS."""

    DESCRIPTION = ("Turns ComfyUI's native GAUSSIAN (TripoSplat, 3D File to Gaussian Splat, ...) into PhysMotion "
                   "Gaussians: each batch item becomes one object of the scene (object ids 0, 1, ...).")

    @classmethod
    def INPUT_TYPES(cls):
        return {"required": {
            "gaussian": (NATIVE_GAUSSIAN_TYPE, {"tooltip": "ComfyUI's GAUSSIAN splats; one batch item per object."}),
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

    DESCRIPTION = ("Turns PhysMotion Gaussians into ComfyUI's native GAUSSIAN, for Render Gaussian Splat, Gaussian "
                   "Splat to 3D File, Merge/Transform Gaussian and the splat preview.")

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
    OUTPUT_TOOLTIPS = ("The Gaussians as ComfyUI's GAUSSIAN (linear scales, wxyz, opacities in [0, 1], SH kept).",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/io"

    def run(self, gaussians, axes, split_objects):
        from physmotion_core.interop_gaussian import to_native

        g = as_pm_gaussians(gaussians).detach()
        return (to_native(g, _NATIVE_CLS, axes=axes, split=bool(split_objects)),)


class PhysMotionSimToGAUSSIAN:
    """PM_SIM -> a GAUSSIAN batch, one item per simulated frame."""

    DESCRIPTION = ("The simulated Gaussians of every frame as one native GAUSSIAN batch (item k = frame k, shaped "
                   "exactly as PhysMotion Render draws it), for Render Gaussian Splat (one image per item), "
                   "Gaussian Splat to 3D File and the splat preview.")

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
        return (_NATIVE_CLS(t["positions"], t["scales"], t["rotations"], t["opacities"], t["sh"],
                            counts=t["counts"]),)


if _NATIVE_CLS is None:
    log.info("PhysMotion: this ComfyUI has no native GAUSSIAN type; the GAUSSIAN converter nodes are not "
             "registered (PhysMotion nodes still take PM_GAUSSIANS)")
    NODE_CLASS_MAPPINGS: dict = {}
    NODE_DISPLAY_NAME_MAPPINGS: dict = {}
else:
    NODE_CLASS_MAPPINGS = {
        "PhysMotionFromGAUSSIAN": PhysMotionFromGAUSSIAN,
        "PhysMotionToGAUSSIAN": PhysMotionToGAUSSIAN,
        "PhysMotionSimToGAUSSIAN": PhysMotionSimToGAUSSIAN,
    }
    NODE_DISPLAY_NAME_MAPPINGS = {
        "PhysMotionFromGAUSSIAN": "PhysMotion GAUSSIAN to PhysMotion Gaussians",
        "PhysMotionToGAUSSIAN": "PhysMotion Gaussians to GAUSSIAN",
        "PhysMotionSimToGAUSSIAN": "PhysMotion Simulation to GAUSSIAN (one item per frame)",
    }
