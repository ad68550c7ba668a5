"""Render every frame of a simulation through a camera."""

from __future__ import annotations

from typing import Optional

import torch

from ..progress import ProgressFn, report
from ..types import Camera, FrameSet, SimResult


def render_frames(sim: SimResult, camera: Camera, *, device: Optional[torch.device | str] = None,
                  progress: Optional[ProgressFn] = None, backend: str = "auto") -> FrameSet:
    """RGB (premultiplied), alpha and expected depth for every simulated frame."""
    from .rasterize import rasterize

    dev = torch.device(device) if device is not None else torch.device("cpu")
    rgb, alpha, depth = [], [], []
    total = sim.num_frames
    with torch.no_grad():
        for k in range(total):
            g = sim.gaussians_at(k).to(dev)
            out = rasterize(g, camera, backend=backend)
            rgb.append(out.rgb.cpu())
            alpha.append(out.alpha.cpu())
            depth.append(out.depth.cpu())
            report(progress, k + 1, total)
    fps = 1.0 / float(sim.times[1] - sim.times[0]) if total > 1 else 24.0
    return FrameSet(rgb=torch.stack(rgb), alpha=torch.stack(alpha), depth=torch.stack(depth), fps=fps)


def depth_to_image(depth: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Depth frames (T,H,W) to a (T,H,W,3) preview/control image: near = bright, empty = black.

    Normalised over the whole clip (not per frame) so brightness does not flicker.
    """
    valid = alpha > 0.5
    if not bool(valid.any()):
        return torch.zeros(depth.shape + (3,))
    inv = torch.where(valid, 1.0 / depth.clamp_min(1e-6), torch.zeros_like(depth))
    lo = inv[valid].min()
    hi = inv[valid].max()
    norm = torch.where(valid, 0.1 + 0.9 * (inv - lo) / (hi - lo).clamp_min(1e-9), torch.zeros_like(inv))
    return norm[..., None].expand(*norm.shape, 3).contiguous()
