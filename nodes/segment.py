"""Segmentation nodes."""

from __future__ import annotations

from ._util import CATEGORY, first_image, first_mask, log


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
            raise ValueError("method is 'mask' but no mask is connected: connect a MASK or choose 'auto'")
        if m is not None and float(m.max() - m.min()) < 0.5:
            # LoadImage gives a uniform (all-zero 64x64) MASK for images without alpha: that is "no mask".
            if method == "mask":
                raise ValueError("method is 'mask' but the connected mask is empty/uniform (the image has no "
                                 "alpha channel?): draw a mask, use an RGBA image, or choose 'auto'")
            log.info("the connected mask is uniform (no alpha channel): segmenting with GrabCut instead")
            m = None
        if method == "grabcut":
            m = None
        if m is not None:
            m = orient_object_mask(m, mask_polarity)
        seg = segment(img, mask=m, method="mask" if m is not None else "grabcut",
                      grabcut_iters=int(grabcut_iterations))
        return (seg.foreground[None], seg.mask[None], seg.background[None])


NODE_CLASS_MAPPINGS = {"PhysMotionSegment": PhysMotionSegment}
NODE_DISPLAY_NAME_MAPPINGS = {"PhysMotionSegment": "PhysMotion Segment (no model)"}
