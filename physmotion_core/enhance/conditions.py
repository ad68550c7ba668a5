"""Frames and ControlNet conditions at the working resolution: resizing, depth, OpenCV Canny edges."""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InputError


def working_size(height: int, width: int, resolution: int, multiple: int = 64) -> tuple[int, int]:
    """(H', W'): the long side scaled to ``resolution``, both rounded to a multiple of ``multiple``
    (the UNet halves the latent three times)."""
    if resolution < multiple:
        raise InputError(f"resolution must be at least {multiple}; got {resolution}")
    s = resolution / max(height, width)
    h = max(multiple, int(round(height * s / multiple)) * multiple)
    w = max(multiple, int(round(width * s / multiple)) * multiple)
    return h, w


def as_frames(frames, name: str = "frames") -> torch.Tensor:
    """(F,H,W,3) float32 in [0,1] from a tensor/array of IMAGE frames, with clear errors."""
    t = torch.as_tensor(np.asarray(frames) if not isinstance(frames, torch.Tensor) else frames).float().cpu()
    if t.ndim == 3:
        t = t[None]
    if t.ndim != 4 or t.shape[-1] not in (3, 4):
        raise InputError(f"{name} must be IMAGE frames [F,H,W,3]; got shape {tuple(t.shape)}")
    t = t[..., :3]
    if t.shape[1] < 8 or t.shape[2] < 8:
        raise InputError(f"{name} are {t.shape[1]}x{t.shape[2]} pixels; need at least 8x8")
    if not bool(torch.isfinite(t).all()):
        raise InputError(f"{name} contain NaN or Inf values")
    return t.clamp(0, 1)


def as_depth(depth, frames: int, name: str = "depth") -> torch.Tensor:
    """(F,H,W) float32 in [0,1] (near = bright, as PhysMotion Render's depth output)."""
    t = torch.as_tensor(np.asarray(depth) if not isinstance(depth, torch.Tensor) else depth).float().cpu()
    if t.ndim == 4:
        t = t[..., :3].mean(-1) if t.shape[-1] in (1, 3, 4) else None
    elif t.ndim == 2:
        t = t[None]
    if t is None or t.ndim != 3:
        raise InputError(f"{name} must be one depth image per frame [F,H,W,3] or a MASK-like [F,H,W]; got "
                         f"shape {tuple(torch.as_tensor(depth).shape)}. Connect PhysMotion Render's depth output.")
    if t.shape[0] != frames:
        raise InputError(f"{name} has {t.shape[0]} images but there are {frames} frames: connect the depth output of "
                         "the same PhysMotion Render node that made the frames.")
    if not bool(torch.isfinite(t).all()):
        raise InputError(f"{name} contains NaN or Inf values")
    return t.clamp(0, 1)


def resize_nchw(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    shrinking = size[0] < x.shape[-2] or size[1] < x.shape[-1]
    return F.interpolate(x, size=size, mode="area" if shrinking else "bilinear",
                         **({} if shrinking else {"align_corners": False}))


def canny_edges(images: torch.Tensor, low: float = 100, high: float = 200) -> torch.Tensor:
    """OpenCV Canny edges (F,3,H,W) in {0,1} of images (F,3,H,W) in [0,1] (ControlNet-canny input)."""
    import cv2

    if not (0 <= low <= high):
        raise InputError(f"canny thresholds need 0 <= low <= high; got low={low}, high={high}")
    out = []
    for img in images:
        u8 = (img.permute(1, 2, 0).numpy() * 255 + 0.5).clip(0, 255).astype(np.uint8)
        gray = cv2.cvtColor(u8, cv2.COLOR_RGB2GRAY)
        e = cv2.Canny(gray, float(low), float(high)) > 0
        out.append(torch.from_numpy(e).float()[None].expand(3, -1, -1))
    return torch.stack(out)


def prepare_conditions(frames: torch.Tensor, depth: Optional[torch.Tensor], size: tuple[int, int],
                       canny_low: float, canny_high: float, want_depth: bool, want_canny: bool):
    """Frames (F,3,H',W') and the depth / canny images (F,3,H',W') (None when not wanted)."""
    imgs = resize_nchw(frames.permute(0, 3, 1, 2).contiguous(), size).clamp(0, 1)
    d = None
    if want_depth:
        if depth is None:
            raise InputError("The depth ControlNet is loaded but no depth was given: connect PhysMotion Render's "
                             "depth output (or load no depth ControlNet).")
        d = resize_nchw(depth[:, None], size).clamp(0, 1).expand(-1, 3, -1, -1).contiguous()
    e = canny_edges(imgs, canny_low, canny_high) if want_canny else None
    return imgs, d, e
