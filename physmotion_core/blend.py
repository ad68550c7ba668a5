"""Image-space compositing of the rendered object over the inpainted background.

The paper blends in image space before inversion (latent-space blending breaks edges), so this is
the coarse video itself: out = rgb_premultiplied + (1 - alpha) * background.
"""

from __future__ import annotations

import torch

from .errors import InputError


def composite(rgb: torch.Tensor, alpha: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Blend premultiplied ``rgb`` (T,H,W,3) with ``alpha`` (T,H,W) over ``background`` (H,W,3) or (T,H,W,3)."""
    if rgb.ndim == 3:
        rgb, alpha = rgb[None], alpha[None]
    if rgb.ndim != 4 or rgb.shape[-1] != 3:
        raise InputError(f"rendered colour must be (T,H,W,3); got {tuple(rgb.shape)}")
    if alpha.shape != rgb.shape[:3]:
        raise InputError(f"alpha {tuple(alpha.shape)} does not match the colour frames {tuple(rgb.shape[:3])}")
    bg = background if background.ndim == 4 else background[None]
    if bg.shape[1:3] != rgb.shape[1:3]:
        raise InputError(f"background is {tuple(bg.shape[1:3])} pixels but the frames are "
                         f"{tuple(rgb.shape[1:3])}; render at the background's size or resize it")
    bg = bg.to(rgb.device, rgb.dtype)
    return (rgb + (1.0 - alpha[..., None]) * bg).clamp(0.0, 1.0)
