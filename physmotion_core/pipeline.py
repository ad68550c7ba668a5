"""The whole chain as one call: image → segment → lift → simulate → render → blend (→ mp4).

This is the no-weights path (classic segmentation, silhouette lift); the learned stages plug in
where their weights are present.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Union

import numpy as np
import torch

from .blend import composite
from .errors import InputError
from .progress import ProgressFn
from .types import Conditions, FrameSet, Gaussians, Ground, Material, SimResult, SimSettings, Camera

log = logging.getLogger("physmotion")

StageProgress = Callable[[str], Optional[ProgressFn]]


@dataclass
class PipelineResult:
    frames: torch.Tensor  # (T,H,W,3) float 0..1: the coarse video
    fps: float
    segmentation: object
    gaussians: Gaussians
    camera: Camera
    sim: SimResult
    render: FrameSet
    timings: dict = field(default_factory=dict)
    video_path: Optional[Path] = None


def generate(
    image: Union[str, Path, torch.Tensor, np.ndarray],
    *,
    conditions: Conditions | None = None,
    material: Union[str, Material] = "jelly",
    material_params: Optional[dict] = None,
    mask: Optional[torch.Tensor] = None,
    ground: Optional[Ground] = Ground(0.0, "friction", 0.5),
    object_height: float = 0.3,
    fov_y_deg: float = 40.0,
    max_gaussians: int = 60_000,
    settings: SimSettings | None = None,
    output: Union[str, Path, None] = None,
    progress: Optional[StageProgress] = None,
) -> PipelineResult:
    """Animate the object in ``image`` under ``conditions`` and return (and optionally save) the video.

    ``ground`` is added to the conditions unless they already contain a Ground; pass None for no
    ground (the object then falls out of the domain floor's reach only as far as its walls allow).
    """
    from .image_io import load_image
    from .lift import silhouette_lift
    from .render.frames import render_frames
    from .segment import segment
    from .sim import simulate

    def stage(name: str) -> Optional[ProgressFn]:
        return progress(name) if progress is not None else None

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    alpha = None
    if isinstance(image, (str, Path)):
        rgb, alpha = load_image(image)
    else:
        rgb = torch.as_tensor(np.asarray(image) if isinstance(image, np.ndarray) else image).float()
        if rgb.ndim != 3 or rgb.shape[-1] not in (3, 4):
            raise InputError(f"image must be (H, W, 3) or (H, W, 4) in 0..1; got shape {tuple(rgb.shape)}")
        if rgb.shape[-1] == 4:
            rgb, alpha = rgb[..., :3], rgb[..., 3]
    settings = settings or SimSettings()
    settings.validate()
    mat = material if isinstance(material, Material) else Material.preset(material, **(material_params or {}))
    conditions = conditions or Conditions()
    if ground is not None and conditions.ground() is None:
        conditions = conditions + ground

    seg = segment(rgb, alpha=alpha, mask=mask)
    timings["segment_s"] = time.perf_counter() - t0

    t = time.perf_counter()
    g_ground = conditions.ground()
    lift = silhouette_lift(seg.image, seg.mask, object_height=object_height, fov_y_deg=fov_y_deg,
                           max_gaussians=max_gaussians, on_ground=g_ground is not None,
                           ground_height=g_ground.height if g_ground is not None else 0.0)
    timings["lift_s"] = time.perf_counter() - t

    t = time.perf_counter()
    sim = simulate(lift.gaussians, mat, conditions, settings, camera=lift.camera, progress=stage("simulate"))
    timings["simulate_s"] = time.perf_counter() - t

    t = time.perf_counter()
    frames = render_frames(sim, lift.camera, progress=stage("render"))
    timings["render_s"] = time.perf_counter() - t

    video = composite(frames.rgb, frames.alpha, seg.background)
    result = PipelineResult(frames=video, fps=settings.fps, segmentation=seg, gaussians=lift.gaussians,
                            camera=lift.camera, sim=sim, render=frames, timings=timings)
    if output is not None:
        from .video import write_mp4

        t = time.perf_counter()
        result.video_path = write_mp4(output, video, fps=settings.fps)
        timings["encode_s"] = time.perf_counter() - t
    timings["total_s"] = time.perf_counter() - t0
    return result
