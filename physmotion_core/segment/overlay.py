"""A picture of what the segmentation chose, to look at before simulating.

Left: the photo with the mask's outline (bright yellow on a dark edge, 3 px at 600 px) and a light
tint outside the mask; object clicks as green dots, background clicks red, the box as a cyan
rectangle, force points as magenta crosses. Right: the background with the object filled in.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from ..errors import InputError
from ..fsutil import atomic_output

OUTLINE = (1.0, 0.92, 0.1)  # bright yellow
OUTLINE_EDGE = (0.0, 0.0, 0.0)
OBJECT_POINT = (0.1, 0.9, 0.2)
BACKGROUND_POINT = (0.95, 0.15, 0.1)
BOX = (0.1, 0.85, 0.95)
FORCE_POINT = (0.95, 0.2, 0.95)
TINT = (0.15, 0.15, 0.45)  # outside the mask the photo is mixed 30% towards this


def _arr(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def mask_overlay(image, mask, background=None, *, object_points=(), background_points=(), box=None,
                 force_points=()) -> np.ndarray:
    """float32 (H, 2W, 3) in 0..1: the outlined photo on the left, ``background`` on the right.

    ``background`` defaults to the photo with the masked region greyed out (when no inpainted
    background is at hand). Points are (x, y) pixels; ``box`` is (x0, y0, x1, y1), x1/y1 exclusive.
    """
    from .classic import as_image_array, as_mask_array

    img = as_image_array(image)
    H, W = img.shape[:2]
    m = as_mask_array(mask, (H, W)) > 0.5
    if background is None:
        bg = np.where(m[:, :, None], np.float32(0.5), img)
    else:
        bg = as_image_array(background, "background")
        if bg.shape != img.shape:
            raise InputError(f"background size {bg.shape[1]}x{bg.shape[0]} does not match the image {W}x{H}")
    left = np.where(m[:, :, None], img, 0.7 * img + 0.3 * np.float32(TINT)).astype(np.float32)
    left = np.ascontiguousarray(left)
    s = max(H, W) / 600.0
    thick = max(2, int(round(3 * s)))
    contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(left, contours, -1, OUTLINE_EDGE, thick + max(2, int(round(2 * s))), cv2.LINE_AA)
    cv2.drawContours(left, contours, -1, OUTLINE, thick, cv2.LINE_AA)
    if box is not None:
        x0, y0, x1, y1 = (int(round(float(v))) for v in box)
        cv2.rectangle(left, (x0, y0), (x1 - 1, y1 - 1), OUTLINE_EDGE, thick + 2)
        cv2.rectangle(left, (x0, y0), (x1 - 1, y1 - 1), BOX, thick)
    r = max(4, int(round(6 * s)))
    for pts, colour in ((object_points, OBJECT_POINT), (background_points, BACKGROUND_POINT)):
        for p in pts if pts is not None else ():
            x, y = (int(round(float(v))) for v in p)
            cv2.circle(left, (x, y), r + max(1, thick // 2), OUTLINE_EDGE, -1, cv2.LINE_AA)
            cv2.circle(left, (x, y), r, colour, -1, cv2.LINE_AA)
    for p in force_points if force_points is not None else ():
        x, y = (int(round(float(v))) for v in p)
        cv2.drawMarker(left, (x, y), OUTLINE_EDGE, cv2.MARKER_TILTED_CROSS, 3 * r, thick + 2)
        cv2.drawMarker(left, (x, y), FORCE_POINT, cv2.MARKER_TILTED_CROSS, 3 * r, thick)
    out = np.concatenate([np.clip(left, 0, 1), np.clip(bg, 0, 1)], axis=1)
    return np.ascontiguousarray(out.astype(np.float32))


CAPTION_BAR = (0.08, 0.08, 0.1)
CAPTION_TEXT = (1.0, 1.0, 1.0)


def with_caption(overlay, lines) -> np.ndarray:
    """The overlay with a dark bar on top holding ``lines`` (wrapped to its width; light text): what the user
    should know when looking at it (the object was picked automatically, what looks wrong). Nothing added
    when ``lines`` is empty."""
    arr = _arr(overlay).astype(np.float32)
    lines = [str(t) for t in lines if str(t).strip()]
    if not lines:
        return arr
    H, W = arr.shape[:2]
    font = cv2.FONT_HERSHEY_SIMPLEX
    scale = max(0.4, min(1.2, W / 1600.0))
    thick = 1 if scale < 0.8 else 2
    (_, th), base = cv2.getTextSize("Ag", font, scale, thick)
    pad = max(4, th // 2)
    wrapped = []
    for text in lines:
        row = ""
        for word in text.split():
            trial = f"{row} {word}".strip()
            if row and cv2.getTextSize(trial, font, scale, thick)[0][0] > W - 2 * pad:
                wrapped.append(row)
                row = word
            else:
                row = trial
        wrapped.append(row)
    step = th + base + pad
    bar = np.empty((pad + step * len(wrapped), W, 3), np.uint8)  # OpenCV draws text on 8-bit images only
    bar[:] = np.round(np.float32(CAPTION_BAR) * 255).astype(np.uint8)
    ink = tuple(int(round(c * 255)) for c in CAPTION_TEXT)
    for i, row in enumerate(wrapped):
        cv2.putText(bar, row, (pad, pad + th + i * step), font, scale, ink, thick, cv2.LINE_AA)
    return np.ascontiguousarray(np.concatenate([bar.astype(np.float32) / 255.0, arr], axis=0))


def write_overlay(path, overlay) -> str:
    """Write an overlay (H, W, 3) float 0..1 (or uint8) as a PNG, atomically; returns the path."""
    arr = _arr(overlay)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise InputError(f"write_overlay: the overlay must be (H, W, 3); got {tuple(arr.shape)}")
    if arr.dtype != np.uint8:
        arr = (np.clip(arr.astype(np.float32), 0, 1) * 255 + 0.5).astype(np.uint8)
    with atomic_output(path, suffix=".tmp.png") as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(arr[:, :, ::-1])):
            raise InputError(f"could not write the overlay PNG to {path}")
    return str(path)
