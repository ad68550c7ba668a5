"""Render every frame of a simulation through a camera."""

from __future__ import annotations

from typing import Optional

import torch

from ..errors import InputError
from ..memory import fmt_bytes, host_available_bytes
from ..progress import ProgressFn, report
from ..types.camera import Camera
from ..types.results import FrameSet, SimResult


#: Bytes per pixel and frame of a rendered clip: RGB + alpha + depth, float32.
FRAME_BYTES_PER_PIXEL = 5 * 4


def frames_bytes(frames: int, width: int, height: int, per_pixel: int = FRAME_BYTES_PER_PIXEL) -> int:
    return int(frames) * int(width) * int(height) * int(per_pixel)


def check_frames_fit(frames: int, width: int, height: int, what: str = "The render",
                     per_pixel: int = FRAME_BYTES_PER_PIXEL, fraction: float = 0.8) -> None:
    """Refuse, before any work, a clip whose frames would not fit in the RAM available now."""
    need = frames_bytes(frames, width, height, per_pixel)
    have = host_available_bytes()
    if need > fraction * have:
        fit = max(int(fraction * have // max(frames_bytes(1, width, height, per_pixel), 1)), 0)
        raise InputError(f"{what} needs about {fmt_bytes(need)} of RAM for {frames} frames of {width}x{height} "
                         f"but only {fmt_bytes(have)} is available. Lower the frame count (at most about {fit} at "
                         "this size) or the image size (e.g. scale the photo down before lifting).")


def render_frames(sim: SimResult, camera: Camera, *, device: Optional[torch.device | str] = None,
                  progress: Optional[ProgressFn] = None, backend: str = "auto") -> FrameSet:
    """RGB (premultiplied), alpha and expected depth for every simulated frame.

    The clip's memory is checked before the first frame (``check_frames_fit``) and the frames are
    written into preallocated tensors, so a clip that fits never needs twice its size.
    """
    from .rasterize import rasterize

    dev = torch.device(device) if device is not None else torch.device("cpu")
    total = sim.num_frames
    W, H = int(camera.width), int(camera.height)
    check_frames_fit(total, W, H)
    rgb = torch.empty(total, H, W, 3)
    alpha = torch.empty(total, H, W)
    depth = torch.empty(total, H, W)
    with torch.no_grad():
        for k in range(total):
            g = sim.gaussians_at(k).to(dev)
            out = rasterize(g, camera, backend=backend)
            rgb[k] = out.rgb.cpu()
            alpha[k] = out.alpha.cpu()
            depth[k] = out.depth.cpu()
            report(progress, k + 1, total)
    fps = 1.0 / float(sim.times[1] - sim.times[0]) if total > 1 else 24.0
    return FrameSet(rgb=rgb, alpha=alpha, depth=depth, fps=fps)


def depth_to_image(depth: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Depth frames (T,H,W) to a (T,H,W,3) preview/control image: near = bright, empty = black.

    Normalised over the whole clip (not per frame) so brightness does not flicker.
    """
    valid = alpha > 0.5
    if not bool(valid.any()):
        return torch.zeros(depth.shape + (3,))
    # In place, in the order of 0.1 + 0.9 (inv - lo) / (hi - lo) (the same values), without the boolean
    # gathers: a Wan clip's depth is tens of millions of pixels.
    invalid = ~valid
    inv = depth.clamp_min(1e-6).reciprocal_().masked_fill_(invalid, 0.0)
    lo = inv.masked_fill(invalid, float("inf")).min()
    hi = inv.max()  # valid pixels have 1/depth > 0, the others 0
    norm = inv.sub_(lo).mul_(0.9).div_((hi - lo).clamp_min(1e-9)).add_(0.1).masked_fill_(invalid, 0.0)
    return norm[..., None].expand(*norm.shape, 3).contiguous()
