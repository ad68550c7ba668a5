"""segment stage: the object's mask, foreground and inpainted background.

The classic (model-free) path lives in ``classic``: alpha channel, a given mask, or GrabCut seeded
by an automatic box. A learned segmenter (SAM) produces a mask and hands it to ``segment`` with
``method="mask"``.
"""

from .classic import (
    Segmentation,
    auto_box,
    clean_mask,
    default_dilate_px,
    grabcut,
    inpaint_background,
    mask_box,
    segment,
)

__all__ = [
    "Segmentation",
    "auto_box",
    "clean_mask",
    "default_dilate_px",
    "grabcut",
    "inpaint_background",
    "mask_box",
    "segment",
]
