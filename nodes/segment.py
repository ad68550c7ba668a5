"""Segmentation nodes."""

from __future__ import annotations

import torch

from physmotion_core.errors import InputError

from ._util import CATEGORY, first_image, first_mask, log, preview_images


class PhysMotionSegment:
    """Split the image into the object (mask, foreground) and an inpainted background."""

    DESCRIPTION = ("Finds the object to animate: uses the given mask (or LoadImage's alpha mask), otherwise "
                   "OpenCV GrabCut around the salient centre. The background has the object's region inpainted, "
                   "so what the moving object uncovers looks plausible.")

    @classmethod
    def INPUT_TYPES(cls):
        from physmotion_core.masks import POLARITIES

        return {
            "required": {
                "image": ("IMAGE", {"tooltip": "The photo containing the object (the first image of a batch is used)."}),
                "method": (["auto", "mask", "grabcut"], {
                    "default": "auto",
                    "tooltip": "auto: the mask if one is connected, else GrabCut. mask: require a mask. "
                               "grabcut: ignore the mask and segment automatically."}),
                "mask_polarity": (list(POLARITIES), {
                    "default": "auto",
                    "tooltip": "LoadImage's MASK is white where the image is transparent (black = object). "
                               "auto detects this from the border."}),
                "grabcut_iterations": ("INT", {"default": 5, "min": 1, "max": 20,
                                               "tooltip": "GrabCut refinement iterations (more = slower, tighter)."}),
            },
            "optional": {
                "mask": ("MASK", {"tooltip": "Optional object mask, e.g. LoadImage's alpha mask."}),
            },
        }

    RETURN_TYPES = ("IMAGE", "MASK", "IMAGE")
    RETURN_NAMES = ("foreground", "mask", "background")
    OUTPUT_TOOLTIPS = ("The object over black.", "1 on the object.", "The photo with the object inpainted away.")
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/segment"

    def run(self, image, method, mask_polarity, grabcut_iterations, mask=None):
        from physmotion_core.masks import orient_object_mask
        from physmotion_core.segment import segment

        img = first_image(image)
        m = first_mask(mask)
        if method == "mask" and m is None:
            raise InputError("method is 'mask' but no mask is connected: connect a MASK or choose 'auto'")
        if m is not None and float(m.max() - m.min()) < 0.5:
            # LoadImage gives a uniform (all-zero 64x64) MASK for images without alpha: that is "no mask".
            if method == "mask":
                raise InputError("method is 'mask' but the connected mask is empty/uniform (the image has no "
                                 "alpha channel?): draw a mask, use an RGBA image, or choose 'auto'")
            log.info("the connected mask is uniform (no alpha channel): segmenting with GrabCut instead")
            m = None
        if method == "grabcut":
            m = None
        if m is not None:
            m = orient_object_mask(m, mask_polarity)
        seg = segment(img, mask=m, method="mask" if m is not None else "grabcut",
                      grabcut_iters=int(grabcut_iterations))
        return {"ui": _segment_preview(seg.foreground, seg.background),
                "result": (seg.foreground[None], seg.mask[None], seg.background[None])}


def _segment_preview(foreground: torch.Tensor, background: torch.Tensor) -> dict:
    """The object over black beside the inpainted background, as one still preview."""
    return preview_images(torch.cat([foreground, background], dim=1)[None], "PhysMotion_segment")


class PhysMotionSAMLoader:
    """Load an official SAM checkpoint (vit_b / vit_l / vit_h, detected from the file) from models/sams/."""

    DESCRIPTION = ("Loads Segment Anything from models/sams/ (sam_vit_h_4b8939.pth, sam_vit_l_0b3195.pth or "
                   "sam_vit_b_01ec64.pth from the official release). The size is read from the file itself. "
                   "Nothing is downloaded.")

    @classmethod
    def INPUT_TYPES(cls):
        from ._util import model_choices

        return {"required": {
            "sam_name": (model_choices("sams", suffixes=(".pth", ".pt", ".safetensors")),
                         {"tooltip": "A checkpoint in models/sams/."}),
        }}

    RETURN_TYPES = ("PM_SAM",)
    RETURN_NAMES = ("sam",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/segment"

    def run(self, sam_name):
        from physmotion_core.segment.sam import OFFICIAL_FILES, load_sam

        from ._memory import manage
        from ._util import model_path, offload_device

        path = model_path("sams", sam_name, expected=" or ".join(OFFICIAL_FILES.values()))
        return (manage(load_sam(str(path), device=offload_device()), "SAM"),)


class PhysMotionSAMSegment:
    """Segment objects with SAM from points and/or boxes (or the most salient object automatically)."""

    DESCRIPTION = ("Masks the object(s) to animate with SAM. Points: 'x, y' on an object, 'x, y, 0' on the "
                   "background, 'x, y, 1, k' for object number k. Boxes: 'x0, y0, x1, y1', one object each. "
                   "Entries are separated by ';' or new lines. No prompt: the most salient object. Of SAM's "
                   "three candidate masks the one with the best predicted IoU is kept; holes and specks are "
                   "cleaned. The background has every object inpainted away.")

    @classmethod
    def INPUT_TYPES(cls):
        return {
            "required": {
                "sam": ("PM_SAM", {"tooltip": "From PhysMotion SAM Loader."}),
                "image": ("IMAGE", {"tooltip": "The photo (the first image of a batch is used)."}),
                "points": ("STRING", {"default": "", "multiline": True,
                                      "tooltip": "Point prompts, e.g. '320, 240; 40, 20, 0' (object point, "
                                                 "background point). Empty: use the boxes, or automatic."}),
                "boxes": ("STRING", {"default": "", "multiline": True,
                                     "tooltip": "Box prompts 'x0, y0, x1, y1', one object per box."}),
                "coordinates": (["pixels", "fraction"], {
                    "default": "pixels",
                    "tooltip": "pixels: as in the image. fraction: 0..1 of the width and height "
                               "(templates that work at any image size)."}),
                "clean": ("BOOLEAN", {"default": True, "tooltip": "Fill small holes and drop specks."}),
            },
        }

    RETURN_TYPES = ("IMAGE", "MASK", "IMAGE", "MASK")
    RETURN_NAMES = ("foreground", "mask", "background", "object_masks")
    OUTPUT_TOOLTIPS = ("Every object over black.", "All objects (1 on an object).",
                       "The photo with every object inpainted away.",
                       "One mask per object, in prompt order (a batch), for multi-object scenes.")
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/segment"

    def run(self, sam, image, points, boxes, coordinates, clean):
        from physmotion_core.segment.sam import parse_prompts, sam_segment

        from ._memory import models_on_device

        img = first_image(image)
        H, W = img.shape[:2]
        prompts = parse_prompts(points, boxes, width=W, height=H, fraction=coordinates == "fraction")
        with models_on_device(sam, what="SAM Segment"):
            res = sam_segment(sam, img, prompts, clean=bool(clean))
        seg = res.segmentation
        return {"ui": _segment_preview(seg.foreground, seg.background),
                "result": (seg.foreground[None], seg.mask[None], seg.background[None], res.masks)}


NODE_CLASS_MAPPINGS = {
    "PhysMotionSegment": PhysMotionSegment,
    "PhysMotionSAMLoader": PhysMotionSAMLoader,
    "PhysMotionSAMSegment": PhysMotionSAMSegment,
}
NODE_DISPLAY_NAME_MAPPINGS = {
    "PhysMotionSegment": "PhysMotion Segment (no model)",
    "PhysMotionSAMLoader": "PhysMotion SAM Loader",
    "PhysMotionSAMSegment": "PhysMotion SAM Segment",
}
