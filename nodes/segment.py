"""Segmentation nodes."""

from __future__ import annotations

import torch

from physmotion_core.errors import InputError

from ._util import CATEGORY, first_image, first_mask, log, preview_images, progress_callback


class PhysMotionSegment:
    """Split the image into the object (mask, foreground) and an inpainted background."""

    DESCRIPTION = ("Finds the object to animate: uses the given mask (LoadImage's alpha mask, or a MASK from any "
                   "other node: ComfyUI's own SAM or background-removal nodes), otherwise OpenCV GrabCut seeded by "
                   "your prompts: click on the picture in the node for an object point, Shift-click for a "
                   "background point, drag for a box. Without prompts GrabCut looks around the salient centre, "
                   "and a mask that does not look like one object (it touches three frame edges, covers most of "
                   "the picture, falls apart in pieces) is refused with the overlay to look at. The background "
                   "has the object's region inpainted, so what the moving object uncovers looks plausible.")

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
                "mask": ("MASK", {"tooltip": "Optional object mask: LoadImage's alpha mask, or the MASK of any other "
                                             "node (ComfyUI's SAM, a background-removal node, the mask editor)."}),
                "object_points": ("STRING", {"default": "", "tooltip": "Pixels (column, row) on the object, 'x, y; "
                                                                       "x, y'. Click on the picture to add one."}),
                "background_points": ("STRING", {"default": "", "tooltip": "Pixels that are NOT the object, 'x, y; "
                                                                           "x, y'. Shift-click on the picture."}),
                "box": ("STRING", {"default": "", "tooltip": "A box around the object 'x0, y0, x1, y1' in pixels. "
                                                             "Drag on the picture."}),
            },
        }

    RETURN_TYPES = ("IMAGE", "MASK", "IMAGE", "IMAGE")
    RETURN_NAMES = ("foreground", "mask", "background", "overlay")
    OUTPUT_TOOLTIPS = ("The object over black.", "1 on the object.", "The photo with the object inpainted away.",
                       "The mask's outline and your prompts over the photo, beside the filled background.")
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/segment"

    def run(self, image, method, mask_polarity, grabcut_iterations, mask=None, object_points="",
            background_points="", box=""):
        from physmotion_core.masks import orient_object_mask
        from physmotion_core.segment import segment

        img = first_image(image)
        H, W = img.shape[:2]
        obj_pts, bg_pts, box_t = parse_grabcut_prompts(object_points, background_points, box, W, H)
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
        pts = obj_pts + bg_pts
        labels = [1] * len(obj_pts) + [0] * len(bg_pts)
        seg = segment(img, mask=m, method="mask" if m is not None else "grabcut", grabcut_iters=int(grabcut_iterations),
                      box=box_t, points=pts or None, point_labels=labels or None, progress=progress_callback())
        prompted = m is not None or bool(obj_pts) or box_t is not None
        from physmotion_core.segment.check import box_past_photo

        note = box_past_photo(box_t, W, H)
        if note:
            log.warning(note)
        if m is not None and (obj_pts or bg_pts or box_t is not None):
            # the picks would otherwise do nothing, silently: an RGBA photo's alpha reaches this node as a MASK
            note = ("Your points and box were not used: the connected MASK (the photo's transparency, or another "
                    "node's mask) is the object. To cut by them, set method to 'grabcut' or disconnect the mask.")
            log.warning(note)
        return checked_segmentation(seg, prompted, obj_pts, bg_pts, box_t,
                                    source="mask" if m is not None else "grabcut", note=note)


def parse_grabcut_prompts(object_points: str, background_points: str, box: str, width: int, height: int):
    """The no-model Segment node's prompt fields as (object points, background points, box or None),
    read and checked with the SAM node's parser (same formats, same messages)."""
    from physmotion_core.segment.sam import parse_prompts

    entries = [e for e in (object_points or "").replace("\n", ";").split(";") if e.strip()]
    bg = [e for e in (background_points or "").replace("\n", ";").split(";") if e.strip()]
    for e in entries + bg:
        if len([v for v in e.replace(",", " ").split() if v]) != 2:
            raise InputError(f"A point is 'x, y' (pixels: column, row); got {e.strip()!r}. Separate points with ';'")
    if bg and not entries and not (box or "").strip():
        raise InputError("Only background points were given: add an object point (click on the object) or a box")
    text = ";".join([e for e in entries] + [f"{e}, 0" for e in bg])
    prompts = parse_prompts(text, box or "", width=width, height=height)
    if len([p for p in prompts if p.box is not None]) > 1:
        raise InputError("Give one box around the object ('x0, y0, x1, y1'); for several objects use the SAM node")
    obj, neg, the_box = [], [], None
    for p in prompts:
        the_box = p.box if p.box is not None else the_box
        for (x, y), lab in zip(p.points, p.labels):
            (obj if lab == 1 else neg).append((float(x), float(y)))
    return obj, list(dict.fromkeys(neg)), the_box


def checked_segmentation(seg, prompted: bool, obj_pts=(), bg_pts=(), box=None, source: str = "grabcut",
                         note: str | None = None) -> dict:
    """The Segment nodes' result: the mask's plausibility check (refused when nobody said which object,
    warned otherwise, with what to change for the prompt given), the overlay as an IMAGE output and as
    the node's preview. ``source``: "grabcut", "sam" or "mask" (a connected MASK); ``note``: one more line
    for the picture's caption."""
    from physmotion_core.segment.check import (NODE_HOW_TO_FIX, NODE_PROMPT_TIP, check_mask, enforce_plausible,
                                               overlay_caption, retry_hint)
    from physmotion_core.segment.overlay import mask_overlay, with_caption

    report = check_mask(seg.mask, object_points=obj_pts, background_points=bg_pts, image=seg.image)
    overlay = torch.as_tensor(mask_overlay(seg.image, seg.mask, seg.background, object_points=obj_pts,
                                           background_points=bg_pts, box=box)).float()
    # The node's picture says what the checks found and whether the object was picked automatically; the
    # IMAGE output stays the plain overlay (the photo's height, for the nodes downstream).
    shown = with_caption(overlay, overlay_caption(report, prompted=prompted, tip=NODE_PROMPT_TIP) + ([note] if note else []))
    preview = preview_images(torch.from_numpy(shown)[None], "PhysMotion_segment")
    if not report.ok:
        shown = preview["images"][0]["filename"] if preview.get("images") else None
        from ._util import temp_directory

        hint = "" if source == "mask" else retry_hint(points=bool(obj_pts), box=box is not None,
                                                      model=source == "sam", node=True)
        enforce_plausible(report, prompted=prompted, overlay=(temp_directory() / shown) if shown else None,
                          how_to_fix=NODE_HOW_TO_FIX, hint=hint)
    log.info("mask: %s", "; ".join(report.summary_lines()))
    if not prompted:
        log.warning("the object was picked automatically (no point, box or mask): check the overlay in the Segment "
                    "node; click on the object (or drag a box) in the node if it is not the one you mean")
    return {"ui": preview, "result": (seg.foreground[None], seg.mask[None], seg.background[None], overlay[None])}


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
            "optional": {
                "mask": ("MASK", {"tooltip": "A mask from any other node (ComfyUI's own SAM, background removal, the "
                                             "mask editor): used as the object's mask instead of running SAM "
                                             "(checked and inpainted the same way)."}),
            },
        }

    RETURN_TYPES = ("IMAGE", "MASK", "IMAGE", "MASK", "IMAGE")
    RETURN_NAMES = ("foreground", "mask", "background", "object_masks", "overlay")
    OUTPUT_TOOLTIPS = ("Every object over black.", "All objects (1 on an object).",
                       "The photo with every object inpainted away.",
                       "One mask per object, in prompt order (a batch), for multi-object scenes.",
                       "The mask's outline and the prompts over the photo, beside the filled background.")
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/segment"

    def run(self, sam, image, points, boxes, coordinates, clean, mask=None):
        from physmotion_core.segment import segment
        from physmotion_core.segment.sam import parse_prompts, sam_segment

        from ._memory import models_on_device

        img = first_image(image)
        H, W = img.shape[:2]
        prompts = parse_prompts(points, boxes, width=W, height=H, fraction=coordinates == "fraction")
        obj = [(float(x), float(y)) for p in prompts for (x, y), lab in zip(p.points, p.labels) if lab == 1]
        neg = list(dict.fromkeys((float(x), float(y)) for p in prompts for (x, y), lab in zip(p.points, p.labels)
                                 if lab == 0))
        box = next((p.box for p in prompts if p.box is not None), None)
        m = first_mask(mask)
        if m is not None and float(m.max() - m.min()) >= 0.5:
            seg = segment(img, mask=m, method="mask")
            note = None
            if prompts:
                note = ("Your points and boxes were not used: the connected MASK (the photo's transparency, or "
                        "another node's mask) is the object. To segment by them with SAM, disconnect the mask.")
                log.warning(note)
            out = checked_segmentation(seg, True, obj, neg, box, source="mask", note=note)
            out["result"] = out["result"][:3] + (seg.mask[None], out["result"][3])
            return out
        with models_on_device(sam, what="SAM Segment"):
            res = sam_segment(sam, img, prompts, clean=bool(clean))
        seg = res.segmentation
        out = checked_segmentation(seg, bool(prompts), obj, neg, box, source="sam")
        out["result"] = out["result"][:3] + (res.masks, out["result"][3])
        return out


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
