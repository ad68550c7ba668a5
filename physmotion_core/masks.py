"""Mask conventions.

ComfyUI's LoadImage returns MASK = 1 - alpha (white where the image is transparent), while an
object mask is white on the object. ``orient_object_mask`` accepts either.
"""

from __future__ import annotations

import logging

import torch

from .errors import InputError

log = logging.getLogger("physmotion")

POLARITIES = ("auto", "white is object", "black is object")


def orient_object_mask(mask: torch.Tensor, polarity: str = "auto") -> torch.Tensor:
    """Return a float mask in [0,1] that is 1 on the object.

    "auto": an object mask is mostly 0 along the image border; a mask that is mostly 1 there is an
    inverted alpha (ComfyUI LoadImage's MASK output) and is flipped, with a log line saying so.
    """
    if polarity not in POLARITIES:
        raise InputError(f"mask polarity must be one of {POLARITIES}; got '{polarity}'")
    m = mask.float().clamp(0, 1)
    if m.ndim != 2:
        raise InputError(f"mask must be 2-D (H, W); got shape {tuple(m.shape)}")
    if polarity == "black is object":
        return 1.0 - m
    if polarity == "white is object":
        return m
    border = torch.cat([m[0], m[-1], m[:, 0], m[:, -1]])
    if float(border.mean()) > 0.5:
        log.info("mask is white along the border: treating it as an inverted alpha (black = object)")
        return 1.0 - m
    return m
