"""segment stage: the object's mask, foreground and inpainted background.

The classic (model-free) path lives in ``classic``: alpha channel, a given mask, or GrabCut seeded
by an automatic box. A learned segmenter (SAM) produces a mask and hands it to ``segment`` with
``method="mask"``.
"""

from .check import CLI_HOW_TO_FIX, NODE_HOW_TO_FIX, MaskReport, check_mask, enforce_plausible, retry_hint
from .classic import (
    Segmentation,
    auto_box,
    check_points,
    clean_mask,
    default_dilate_px,
    grabcut,
    inpaint_background,
    mask_box,
    segment,
)

from .overlay import mask_overlay, write_overlay

__all__ = [
    "CLI_HOW_TO_FIX",
    "MaskReport",
    "NODE_HOW_TO_FIX",
    "Segmentation",
    "auto_box",
    "check_mask",
    "check_points",
    "enforce_plausible",
    "retry_hint",
    "mask_overlay",
    "write_overlay",
    "clean_mask",
    "default_dilate_px",
    "grabcut",
    "inpaint_background",
    "mask_box",
    "segment",
]
