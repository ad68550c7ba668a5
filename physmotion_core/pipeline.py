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
from .types.camera import Camera
from .types.conditions import Conditions, Ground
from .types.gaussians import Gaussians
from .types.material import Material
from .types.results import FrameSet, SimResult
from .types.settings import SimSettings

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
    stages: dict = field(default_factory=dict)  # which path each stage took, e.g. {"segment": "sam", "lift": "lgm"}


MODEL_CHOICES = ("auto", "none")


def _pick(names: list[str], preferred: tuple[str, ...]) -> Optional[str]:
    for want in preferred:
        for n in names:
            if want in n:
                return n
    return names[0] if names else None


def available_models() -> dict:
    """The learned models the models root (``$PHYSMOTION_MODELS``) holds, by stage."""
    from .models import list_models

    return {"sam": _pick(list_models("sams", suffixes=(".pth", ".pt", ".safetensors")), ("vit_h", "vit_l", "vit_b")),
            "lgm": _pick(list_models("lgm", suffixes=(".safetensors",)), ("fixrot",)),
            "imagedream": _pick(list_models("imagedream", dirs=True), ("imagedream",))}


DEFAULT_MAX_SIDE = 1024  # pixels: larger photos are scaled down first (CPU-friendly; 0 keeps them)


def _resize(t: torch.Tensor, w: int, h: int) -> torch.Tensor:
    """(H,W[,C]) float tensor to (h,w[,C]) with area averaging (no aliasing when shrinking)."""
    import cv2

    arr = cv2.resize(t.detach().float().cpu().numpy(), (w, h), interpolation=cv2.INTER_AREA)
    return torch.from_numpy(np.ascontiguousarray(arr))


def _scale_image_regions(conditions: Conditions, scale: float, size_hw: tuple[int, int]) -> Conditions:
    """Image-space regions (pixel points, radii, masks) given for the full-size photo, mapped onto
    the scaled one."""
    import dataclasses

    from .types.conditions import Region

    out = []
    for c in conditions:
        r = getattr(c, "region", None)
        if isinstance(r, Region) and r.kind == "image":
            m = r.mask
            if m is not None:
                m = _resize(torch.as_tensor(np.asarray(m), dtype=torch.float32), size_hw[1], size_hw[0]).numpy()
            r = dataclasses.replace(r, points=tuple((u * scale, v * scale) for u, v in r.points),
                                    radius_px=r.radius_px * scale, mask=m)
            c = dataclasses.replace(c, region=r)
        out.append(c)
    return Conditions(out)


def _as_rgb_tensor(image) -> torch.Tensor:
    """An in-memory image as float (H,W,C) in 0..1: integer pixels are divided by their type's
    maximum (8-bit by 255, 16-bit by 65535); float pixels must already be in 0..1."""
    arr = image.detach().cpu().numpy() if isinstance(image, torch.Tensor) else np.asarray(image)
    if arr.dtype == bool:
        raise InputError("image is a boolean array; pass the photo, and give a mask through mask=")
    if np.issubdtype(arr.dtype, np.integer):
        top = np.iinfo(arr.dtype).max
        return torch.from_numpy(arr.astype(np.float32) / float(top))
    if not np.issubdtype(arr.dtype, np.floating):
        raise InputError(f"image must hold numbers; got dtype {arr.dtype}")
    t = torch.from_numpy(np.ascontiguousarray(arr, dtype=np.float32))
    if not torch.isfinite(t).all():
        raise InputError("image contains NaN or Inf values; pass an image with values in 0..1")
    lo, hi = float(t.min()), float(t.max())
    if lo < -1e-3 or hi > 1 + 1e-3:
        raise InputError(f"image values must be in 0..1 (found {lo:.3g}..{hi:.3g}); divide 8-bit data by 255 "
                         "or pass the uint8 array itself")
    return t.clamp(0.0, 1.0)


def _check_condition_windows(conditions: Optional[Conditions], settings: SimSettings) -> None:
    """A force, torque or anchor whose time window starts after the clip's last frame changes
    nothing: refuse it rather than silently making a video without it."""
    if not conditions:
        return
    last = (int(settings.frames) - 1) / float(settings.fps)  # frames are at t = k / fps
    for c in conditions:
        t_start = getattr(c, "t_start", None)
        if t_start is not None and float(t_start) > 0 and float(t_start) >= last:
            raise InputError(
                f"{type(c).__name__} acts from t = {float(t_start):.4g} s, but the clip's last frame is at "
                f"t = {last:.4g} s ({settings.frames} frames at {settings.fps:g} fps): it would change nothing. Start it "
                "earlier (--force-time T0,T1) or make the clip longer (more frames).")


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
    max_side: int = DEFAULT_MAX_SIDE,
    models: str = "auto",
    seed: int = 0,
    multiview_steps: int = 30,
    lgm_input_size: int = 256,
    object_point: Optional[tuple[float, float]] = None,
) -> PipelineResult:
    """Animate the object in ``image`` under ``conditions`` and return (and optionally save) the video.

    ``ground`` is added to the conditions unless they already contain a Ground; pass None for no
    ground (the object then falls out of the domain floor's reach only as far as its walls allow).

    ``max_side``: a photo whose long side is larger is scaled down to it first (logged), with its
    alpha and mask, and pixel regions (``Region.at_pixel``) refer to the scaled image; 0 keeps the
    full size. The clip's memory is checked before the simulation starts.

    ``models="auto"`` uses the learned stages whose weights are in the models root and skips what
    the scene does not need: an alpha channel or a mask → no segmentation model; else SAM (its
    most salient object) if present, else GrabCut. LGM + ImageDream both present → the learned lift
    (``seed``, ``multiview_steps``, ``lgm_input_size``), else the silhouette lift. ``"none"`` never
    loads a model. ``result.stages`` says which path each stage took. ``object_point`` (u, v pixels
    of the photo as given) prompts SAM with a point on the object instead of its automatic mode; when
    SAM's automatic mode finds no object, GrabCut takes over (logged).
    """
    from .image_io import load_image
    from .lift import silhouette_lift
    from .render.frames import render_frames
    from .segment import segment
    from .sim import simulate

    def stage(name: str) -> Optional[ProgressFn]:
        return progress(name) if progress is not None else None

    from .fsutil import check_outputs, protect_inputs

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if output is not None:
        # Every output location is checked before any work (a writable folder, a name the file
        # system takes, a video extension this writes, never the input photo itself).
        from .video import video_format

        check_outputs({"output": output}, inputs=[image if isinstance(image, (str, Path)) else None])
        video_format(output)
    alpha = None
    if isinstance(image, (str, Path)):
        rgb, alpha = load_image(image)
    else:
        rgb = _as_rgb_tensor(image)
        if rgb.ndim != 3 or rgb.shape[-1] not in (3, 4):
            raise InputError(f"image must be (H, W, 3) or (H, W, 4) in 0..1; got shape {tuple(rgb.shape)}")
        if rgb.shape[-1] == 4:
            rgb, alpha = rgb[..., :3], rgb[..., 3]
    settings = settings or SimSettings()
    settings.validate()
    _check_condition_windows(conditions, settings)
    if models not in MODEL_CHOICES:
        raise InputError(f"models must be one of {MODEL_CHOICES} ('auto' uses the weights found in the models "
                         f"folder, 'none' never loads a model); got {models!r}")
    found = available_models() if models == "auto" else {"sam": None, "lgm": None, "imagedream": None}
    if isinstance(max_side, bool) or not isinstance(max_side, int) or max_side < 0 or 0 < max_side < 16:
        raise InputError(f"max_side must be 0 (keep the photo's size) or an integer >= 16 pixels; got {max_side!r}")
    if not torch.isfinite(rgb).all():
        raise InputError("image contains NaN or Inf values; pass an image with values in 0..1")
    H, W = int(rgb.shape[0]), int(rgb.shape[1])
    H0, W0 = H, W
    if max_side and max(H, W) > max_side:
        scale = max_side / max(H, W)
        w, h = max(1, round(W * scale)), max(1, round(H * scale))
        log.warning("image is %dx%d: scaled down to %dx%d (max_side=%d; pass max_side=0 to keep the full size)",
                    W, H, w, h, max_side)
        rgb = _resize(rgb, w, h)
        alpha = None if alpha is None else _resize(alpha, w, h)
        if mask is not None:
            mask = _resize(torch.as_tensor(np.asarray(mask), dtype=torch.float32), w, h)
        H, W = h, w
        if conditions is not None:
            conditions = _scale_image_regions(conditions, scale, (h, w))
    # The whole run (segment, lift, simulate, render colour/alpha/depth, composite, encode) must fit
    # before anything runs: an estimate calibrated on measured peaks (memory.pipeline_need_bytes).
    from .memory import check_pipeline_fits

    check_pipeline_fits(W, H, settings.frames, "This video")
    mat = material if isinstance(material, Material) else Material.preset(material, **(material_params or {}))
    conditions = conditions or Conditions()
    if ground is not None and conditions.ground() is None:
        conditions = conditions + ground

    stages: dict[str, str] = {}
    from .models import default_dtype, pick_device

    device = pick_device()
    if alpha is None and mask is None and found["sam"]:
        from .segment.sam import load_sam, sam_segment

        from .segment.sam import ObjectPrompt

        prompts = []
        if object_point is not None:
            u, v = float(object_point[0]) * W / W0, float(object_point[1]) * H / H0  # into the scaled photo
            prompts = [ObjectPrompt(points=[(u, v)], labels=[1])]
        log.info("segmenting with SAM (%s): %s", found["sam"], "the prompted point" if prompts else
                 "the most salient object")
        sam = load_sam(found["sam"], device=device)
        try:
            seg = sam_segment(sam, rgb, prompts).segmentation
            stages["segment"] = "sam"
        except InputError as exc:
            if prompts:
                raise
            log.warning("SAM: %s; segmenting with GrabCut instead", exc)
            seg = segment(rgb)
            stages["segment"] = "grabcut"
        del sam
    else:
        seg = segment(rgb, alpha=alpha, mask=mask)
        stages["segment"] = "alpha" if alpha is not None and mask is None else "mask" if mask is not None else "grabcut"
    timings["segment_s"] = time.perf_counter() - t0

    t = time.perf_counter()
    g_ground = conditions.ground()
    if found["lgm"] and found["imagedream"]:
        from .lift.imagedream import load_imagedream
        from .lift.learned import learned_lift
        from .lift.lgm import load_lgm

        log.info("lifting with ImageDream (%s) + LGM (%s)", found["imagedream"], found["lgm"])
        dtype = default_dtype(device)
        lgm = load_lgm(found["lgm"], device=device, dtype=dtype, input_size=int(lgm_input_size))
        dream = load_imagedream(found["imagedream"], device=device, dtype=dtype)
        lift = learned_lift(rgb, seg.mask, lgm=lgm, imagedream=dream, object_height=object_height,
                            on_ground=g_ground is not None, ground_height=g_ground.height if g_ground is not None else 0.0,
                            seed=int(seed), steps=int(multiview_steps), max_gaussians=int(max_gaussians),
                            progress=stage("lift"))
        del lgm, dream
        stages["lift"] = "lgm"
    else:
        if models == "auto" and (found["lgm"] or found["imagedream"]):
            log.warning("the learned lift needs both LGM and ImageDream weights (found only %s): using the "
                        "silhouette lift", "LGM" if found["lgm"] else "ImageDream")
        lift = silhouette_lift(seg.image, seg.mask, object_height=object_height, fov_y_deg=fov_y_deg,
                               max_gaussians=max_gaussians, on_ground=g_ground is not None,
                               ground_height=g_ground.height if g_ground is not None else 0.0)
        stages["lift"] = "silhouette"
    timings["lift_s"] = time.perf_counter() - t

    t = time.perf_counter()
    sim = simulate(lift.gaussians, mat, conditions, settings, camera=lift.camera, progress=stage("simulate"))
    timings["simulate_s"] = time.perf_counter() - t

    t = time.perf_counter()
    frames = render_frames(sim, lift.camera, progress=stage("render"))
    timings["render_s"] = time.perf_counter() - t

    video = composite(frames.rgb, frames.alpha, seg.background)
    result = PipelineResult(frames=video, fps=settings.fps, segmentation=seg, gaussians=lift.gaussians,
                            camera=lift.camera, sim=sim, render=frames, timings=timings, stages=stages)
    if output is not None:
        from .video import write_mp4

        t = time.perf_counter()
        with protect_inputs(image if isinstance(image, (str, Path)) else None):
            result.video_path = write_mp4(output, video, fps=settings.fps)
        timings["encode_s"] = time.perf_counter() - t
    timings["total_s"] = time.perf_counter() - t0
    return result
