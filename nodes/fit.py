"""Fit Gaussians from any lift (TripoSplat, a .ply, LGM, SAM 3D Objects) to the photo."""

from __future__ import annotations

from ._gaussian_io import GAUSSIANS_INPUT, GAUSSIANS_TOOLTIP_SUFFIX, SPLAT_AXES_INPUT, as_pm_gaussians
from ._util import CATEGORY, first_image, first_mask, log, preview_images, preview_payload, progress_callback


def fit_levels(max_render_side: int) -> tuple:
    """The coarse-to-fine schedule ((max side px, Adam steps), ...) ending at ``max_render_side``."""
    side = int(max_render_side)
    if side <= 48:
        return ((side, 40),)
    if side <= 96:
        return ((48, 30), (side, 30))
    return ((48, 30), (96, 30), (side, 20))


class PhysMotionFitGaussiansToPhoto:
    """Rotate, scale and place any Gaussians so that they line up with the photo's object."""

    DESCRIPTION = ("Lines Gaussians made by any tool (TripoSplat, a .ply from a 3DGS tool, LGM, SAM 3D Objects; any "
                   "axes, units and centring) up with the photo: a search over the usual canonical frames, then "
                   "gradient refinement of rotation, scale, position and focal length against the mask's silhouette "
                   "and the photo's colours. The result stands on the ground at the object's real height, with the "
                   "camera that reproduces the photo. Below the IoU threshold the node stops with an error and shows "
                   "the overlay (mask green, render red) instead of simulating a misaligned object; likewise when the outline matches but the colours do not.")

    @classmethod
    def INPUT_TYPES(cls):
        return {
            "required": {
                "gaussians": (GAUSSIANS_INPUT, {"tooltip": "The Gaussians to fit, in their own frame and units."
                                                           + GAUSSIANS_TOOLTIP_SUFFIX}),
                "image": ("IMAGE", {"tooltip": "The photo the Gaussians were made from (the first of a batch)."}),
                "mask": ("MASK", {"tooltip": "The object's mask in the photo (1 on the object), e.g. from "
                                             "PhysMotion Segment."}),
                "object_height": ("FLOAT", {"default": 0.3, "min": 0.001, "max": 1000.0, "step": 0.01,
                                            "tooltip": "Real height of the object in metres; the fitted object is "
                                                       "scaled to it (it sets the time scale of the physics)."}),
                "iou_threshold": ("FLOAT", {"default": 0.85, "min": 0.0, "max": 1.0, "step": 0.01,
                                            "tooltip": "The fit must cover the mask with at least this IoU, or the "
                                                       "node stops with an error and the overlay. Lower it to "
                                                       "accept a rough fit; 0 accepts anything."}),
                "max_color_error": ("FLOAT", {"default": 0.15, "min": 0.0, "max": 1.0, "step": 0.01,
                                              "tooltip": "... and the mean colour difference over the mask "
                                                         "(0..1) must be at most this: a matching outline with "
                                                         "wrong colours means the object is turned the wrong way "
                                                         "or is another object. 0 = not checked."}),
                "on_ground": ("BOOLEAN", {"default": True,
                                          "tooltip": "Put the object's lowest Gaussian on the ground plane y = 0 "
                                                     "(off: centre it on y = 0)."}),
                "max_render_side": ("INT", {"default": 160, "min": 32, "max": 1024, "step": 16,
                                            "tooltip": "The finest fitting resolution (longest side, px). Higher is "
                                                       "slower and a little more precise."}),
                "seed": ("INT", {"default": 0, "min": 0, "max": 2 ** 31 - 1,
                                 "tooltip": "Seeds the Gaussian subsets used while fitting (same seed, same fit)."}),
            },
            "optional": {
                "focal_px": ("FLOAT", {"default": 0.0, "min": 0.0, "max": 100000.0, "step": 1.0,
                                       "tooltip": "The photo's focal length in pixels (fx = fy). 0 = fit it, "
                                                  "starting from a 40° vertical field of view."}),
                "principal_x": ("FLOAT", {"default": -1.0, "min": -1.0, "max": 100000.0, "step": 1.0,
                                          "tooltip": "Principal point x in pixels; negative = the image centre."}),
                "principal_y": ("FLOAT", {"default": -1.0, "min": -1.0, "max": 100000.0, "step": 1.0,
                                          "tooltip": "Principal point y in pixels; negative = the image centre."}),
                "splat_axes": SPLAT_AXES_INPUT,
            },
        }

    RETURN_TYPES = ("PM_GAUSSIANS", "PM_CAMERA", "IMAGE", "FLOAT", "STRING")
    RETURN_NAMES = ("gaussians", "camera", "overlay", "iou", "report")
    OUTPUT_TOOLTIPS = ("The Gaussians in the world: metres, +y up, on the ground, lined up with the photo.",
                       "The camera that reproduces the photo (level, looking down -z).",
                       "The fitted render over the photo, beside the silhouettes (mask green, render red).",
                       "Final IoU of the rendered silhouette with the mask.",
                       "What the fit found (IoU, colour error, focal, rotation, scale, time).")
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/lift"

    def run(self, gaussians, image, mask, object_height, iou_threshold, max_color_error, on_ground, max_render_side,
            seed, focal_px=0.0, principal_x=-1.0, principal_y=-1.0, splat_axes="y_down"):
        from physmotion_core.lift.fit import FitError, fit_gaussians_to_photo

        img = first_image(image)
        m = first_mask(mask)
        H, W = int(img.shape[0]), int(img.shape[1])
        pp = None
        if float(principal_x) >= 0 or float(principal_y) >= 0:
            pp = (float(principal_x) if float(principal_x) >= 0 else W / 2.0,
                  float(principal_y) if float(principal_y) >= 0 else H / 2.0)
        cb = progress_callback()
        res = fit_gaussians_to_photo(
            as_pm_gaussians(gaussians, axes=splat_axes), img, m, object_height=float(object_height),
            focal=float(focal_px) if float(focal_px) > 0 else None, principal_point=pp,
            iou_threshold=float(iou_threshold), max_color_error=float(max_color_error), on_ground=bool(on_ground), levels=fit_levels(max_render_side),
            seed=int(seed), progress=cb)
        overlay = res.overlay[None]
        ui = preview_images(overlay, "PhysMotion_fit")
        text = res.report()
        if not res.ok:
            # A raised error drops the node's ui result, so the overlay goes out with the progress bar's
            # preview (it stays on the node) and its file is named in the message.
            if cb is not None:
                cb(1, 1, preview_payload(res.overlay))
            where = ui["images"][0]["filename"]
            raise FitError(f"Fit Gaussians to Photo: {res.message} The overlay is shown on the node "
                           f"(temp file {where}). {text.splitlines()[-1]}", res)
        log.info("Fit Gaussians to Photo: %s", text.replace("\n", " "))
        ui["text"] = [text]
        return {"ui": ui, "result": (res.gaussians, res.camera, overlay, float(res.iou), text)}


NODE_CLASS_MAPPINGS = {"PhysMotionFitGaussiansToPhoto": PhysMotionFitGaussiansToPhoto}
NODE_DISPLAY_NAME_MAPPINGS = {"PhysMotionFitGaussiansToPhoto": "PhysMotion Fit Gaussians to Photo"}
