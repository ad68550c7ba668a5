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
    notes: list = field(default_factory=list)  # what the user was told: mask, support, mass, forecast, warnings
    mask_report: object = None  # segment.check.MaskReport of the mask that was simulated
    support: object = None  # support.SupportPlan: what held the object
    motion: object = None  # feedback.MotionReport: largest motion, whether it left the frame


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


@dataclass
class Prepared:
    """Everything decided before the simulation: what ``generate(preview=True)`` returns and
    ``physmotion generate --preview`` prints. ``lines`` are the sentences the user is told (the
    mask's summary, what holds the object, its mass and what each load will roughly do)."""

    segmentation: object
    mask_report: object  # segment.check.MaskReport
    support: object  # support.SupportPlan
    gaussians: Optional[Gaussians]
    camera: Optional[Camera]
    material: Material
    conditions: Conditions
    settings: SimSettings
    stages: dict
    lines: list = field(default_factory=list)
    overlay_path: Optional[Path] = None
    mass_kg: Optional[float] = None
    lift: object = None
    timings: dict = field(default_factory=dict)


def _prompt_points(points, what: str) -> list[tuple[float, float]]:
    out = []
    for p in points or ():
        try:
            u, v = (float(c) for c in p)
        except (TypeError, ValueError):
            raise InputError(f"each {what} is a pair (u, v) of pixel coordinates; got {p!r}") from None
        if not (np.isfinite(u) and np.isfinite(v)):
            raise InputError(f"{what} ({u}, {v}) is not finite")
        out.append((u, v))
    return out


def _check_prompts_inside(points, box, W: int, H: int) -> None:
    for what, pts in points.items():
        for u, v in pts:
            if not (0 <= u <= W and 0 <= v <= H):
                raise InputError(f"the {what} ({u:g}, {v:g}) lies outside the {W}x{H} photo; give pixel coordinates "
                                 "(column, row) of the photo as given")
    if box is not None:
        try:
            x0, y0, x1, y1 = (float(c) for c in box)
        except (TypeError, ValueError):
            raise InputError(f"the box is four numbers X0,Y0,X1,Y1 in pixels; got {box!r}") from None
        if not all(np.isfinite([x0, y0, x1, y1])):
            raise InputError(f"the box {box!r} has a non-finite number")
        if not (x1 > x0 and y1 > y0):
            raise InputError(f"the box ({x0:g}, {y0:g}, {x1:g}, {y1:g}) is empty: X1 must exceed X0 and Y1 exceed Y0")
        if x1 <= 0 or y1 <= 0 or x0 >= W or y0 >= H:
            raise InputError(f"the box ({x0:g}, {y0:g}, {x1:g}, {y1:g}) lies outside the {W}x{H} photo")


def _force_points(conditions: Optional[Conditions]) -> list[tuple[float, float]]:
    pts = []
    for c in conditions or ():
        r = getattr(c, "region", None)
        if r is not None and getattr(r, "kind", None) == "image":
            pts.extend((float(u), float(v)) for u, v in r.points)
    return pts


def _check_regions_reach(conditions: Conditions, mask: torch.Tensor, back: float = 1.0) -> None:
    """A push, twist or throw placed off the object is refused now, with where the object is, not after
    the lift and the fill."""
    m = mask.detach().cpu().numpy() > 0.5
    if not m.any():
        return
    ys, xs = np.nonzero(m)
    box = [int(round(b * back)) for b in (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)]
    for c in conditions:
        r = getattr(c, "region", None)
        if r is None or getattr(r, "kind", None) != "image" or not r.points:
            continue
        rad = float(r.radius_px)
        for u, v in r.points:
            d2 = (xs - float(u)) ** 2 + (ys - float(v)) ** 2
            if float(d2.min()) > rad * rad:
                cx, cy = float(xs.mean()) * back, float(ys.mean()) * back
                raise InputError(
                    f"The {type(c).__name__.lower()} at pixel ({float(u) * back:.0f}, {float(v) * back:.0f}) (radius "
                    f"{rad * back:.0f} px) does not touch the object: its mask spans x {box[0]}..{box[2]}, y "
                    f"{box[1]}..{box[3]} (centre about ({cx:.0f}, {cy:.0f})), "
                    f"{float(np.sqrt(d2.min())) * back:.0f} px away at the nearest. Put the point on the object, or "
                    "look at the mask first with `physmotion segment IMAGE -o overlay.png`.")


def segment_photo(rgb: torch.Tensor, *, alpha=None, mask=None, box=None, object_points=(), background_points=(),
                  sam_name: Optional[str] = None, device=None, progress=None) -> tuple[object, str]:
    """The object's segmentation and which path made it ("alpha", "mask", "sam", "grabcut"):
    an alpha channel or a mask is taken as given; else SAM when ``sam_name`` names its weights (the
    prompts, or its most salient object without any); else GrabCut seeded by the box and points (or
    the automatic box). Points and the box are pixels of ``rgb``. ``progress`` follows GrabCut (its
    iterations; it raises to cancel)."""
    from .segment import segment

    prompted = bool(object_points) or box is not None
    if alpha is not None or mask is not None:
        seg = segment(rgb, alpha=alpha, mask=mask)
        return seg, ("alpha" if alpha is not None and mask is None else "mask")
    if sam_name:
        from .segment.sam import ObjectPrompt, load_sam, sam_segment

        prompts = []
        if prompted or background_points:
            pts = list(object_points) + list(background_points)
            prompts = [ObjectPrompt(points=pts, labels=[1] * len(object_points) + [0] * len(background_points),
                                    box=None if box is None else tuple(float(c) for c in box))]
            if not object_points and box is None:
                raise InputError("only background points were given: add an object point or a box")
        log.info("segmenting with SAM (%s): %s", sam_name, "the prompts" if prompts else "the most salient object")
        sam = load_sam(sam_name, device=device)
        try:
            return sam_segment(sam, rgb, prompts).segmentation, "sam"
        except InputError as exc:
            if prompts:
                raise
            log.warning("SAM: %s; segmenting with GrabCut instead", exc)
        finally:
            del sam
    pts = list(object_points) + list(background_points)
    labels = [1] * len(object_points) + [0] * len(background_points)
    seg = segment(rgb, box=box, points=pts or None, point_labels=labels or None, progress=progress)
    return seg, "grabcut"


def unused_prompts_line(how: str, *, box=None, object_points=(), background_points=()) -> Optional[str]:
    """What to tell a user whose points or box did not cut the mask because the photo's alpha channel or a
    given mask is the object (``how`` from ``segment_photo``); None when nothing was given or it was used."""
    given = [name for name, v in (("--box", box is not None), ("--object-point", bool(object_points)),
                                  ("--background-point", bool(background_points))) if v]
    if how not in ("alpha", "mask") or not given:
        return None
    source, fix = (("the photo's transparency (its alpha channel) is the object's mask",
                    "give the photo without transparency (a JPEG, or the PNG flattened)") if how == "alpha" else
                   ("the --mask file is the object's mask", "leave out --mask"))
    one = len(given) == 1
    return (f"note: {' and '.join(given)} {'was' if one else 'were'} not used to cut the mask: {source}. "
            f"To segment by {'it' if one else 'them'} instead, {fix}.")


def _overlay_default(output) -> Optional[Path]:
    if output is None:
        return None
    out = Path(output)
    return out.with_name(out.stem + ".mask.png")


def prepare(
    image: Union[str, Path, torch.Tensor, np.ndarray],
    *,
    conditions: Conditions | None = None,
    material: Union[str, Material] = "jelly",
    material_params: Optional[dict] = None,
    mask: Optional[torch.Tensor] = None,
    ground: Optional[Ground] = Ground(0.0, "friction", 0.5),
    object_height: Optional[float] = None,
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
    object_points=(),
    background_points=(),
    box: Optional[tuple[float, float, float, float]] = None,
    hold_edges: bool = True,
    overlay: Union[str, Path, None] = None,
    report: Optional[Callable[[str], None]] = None,
    _weigh: bool = True,
):
    """Everything before the simulation (see ``generate``); returns a ``Prepared``."""
    from .image_io import load_image
    from .lift import silhouette_lift
    from .segment.check import CLI_HOW_TO_FIX, check_mask, enforce_plausible, retry_hint

    def stage(name: str) -> Optional[ProgressFn]:
        return progress(name) if progress is not None else None

    lines: list[str] = []

    def say(text: str, warn: bool = False) -> None:
        """Tell the user: through ``report`` when given (the CLI prints it), else the log (warnings at
        WARNING level, the rest at INFO)."""
        lines.append(("warning: " if warn else "") + text)
        if report is not None:
            report(lines[-1])
        elif warn:
            log.warning("%s", text)
        else:
            log.info("%s", text)

    from .fsutil import check_outputs

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if output is not None or overlay is not None:
        # Every output location is checked before any work (a writable folder, a name the file
        # system takes, a video extension this writes, never the input photo itself).
        check_outputs({"output": output, "overlay": overlay},
                      inputs=[image if isinstance(image, (str, Path)) else None])
        if output is not None:
            from .video import video_format

            video_format(output)
    height_given = object_height is not None
    object_height = 0.3 if object_height is None else object_height
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
    obj_pts = _prompt_points(object_points, "object point")
    if object_point is not None:
        obj_pts += _prompt_points([object_point], "object point")
    bg_pts = _prompt_points(background_points, "background point")
    if bg_pts and not obj_pts and box is None and mask is None and alpha is None:
        raise InputError("only background points were given: add an object point (--object-point U,V) or a box "
                         "(--box X0,Y0,X1,Y1) so the segmentation knows which object you mean")
    found = available_models() if models == "auto" else {"sam": None, "lgm": None, "imagedream": None}
    if isinstance(max_side, bool) or not isinstance(max_side, int) or max_side < 0 or 0 < max_side < 16:
        raise InputError(f"max_side must be 0 (keep the photo's size) or an integer >= 16 pixels; got {max_side!r}")
    if not torch.isfinite(rgb).all():
        raise InputError("image contains NaN or Inf values; pass an image with values in 0..1")
    H, W = int(rgb.shape[0]), int(rgb.shape[1])
    W0 = W
    _check_prompts_inside({"object point": obj_pts, "background point": bg_pts}, box, W, H)
    from .segment.check import box_past_photo

    box_note = box_past_photo(box, W, H)  # in the photo's own pixels, before any scaling
    if max_side and max(H, W) > max_side:
        scale = max_side / max(H, W)
        w, h = max(1, round(W * scale)), max(1, round(H * scale))
        log.warning("image is %dx%d: scaled down to %dx%d (max_side=%d; pass max_side=0 to keep the full size)",
                    W, H, w, h, max_side)
        rgb = _resize(rgb, w, h)
        alpha = None if alpha is None else _resize(alpha, w, h)
        if mask is not None:
            mask = _resize(torch.as_tensor(np.asarray(mask), dtype=torch.float32), w, h)
        if conditions is not None:
            conditions = _scale_image_regions(conditions, scale, (h, w))
        sx, sy = w / W, h / H
        obj_pts = [(u * sx, v * sy) for u, v in obj_pts]
        bg_pts = [(u * sx, v * sy) for u, v in bg_pts]
        if box is not None:
            box = (box[0] * sx, box[1] * sy, box[2] * sx, box[3] * sy)
        H, W = h, w
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
    if alpha is not None and float(alpha.min()) >= 1.0 - 0.5 / 255.0:
        alpha = None  # fully opaque: it says nothing about the object
    seg, stages["segment"] = segment_photo(rgb, alpha=alpha, mask=mask, box=box, object_points=obj_pts,
                                           background_points=bg_pts, sam_name=found["sam"], device=device,
                                           progress=stage("segment") if alpha is None and mask is None else None)
    timings["segment_s"] = time.perf_counter() - t0

    _check_regions_reach(conditions, seg.mask, back=W0 / W)
    # Is it plausibly one object? Checked for every mask; refused only when nobody said which object.
    given = stages["segment"] in ("alpha", "mask") or bool(obj_pts) or box is not None
    force_pts = _force_points(conditions)
    mask_report = check_mask(seg.mask, object_points=obj_pts, background_points=bg_pts, force_points=force_pts,
                             image=seg.image)
    overlay_path = Path(overlay) if overlay is not None else None
    if overlay_path is None and (not mask_report.ok or not given):
        overlay_path = _overlay_default(output)
    if overlay_path is not None:
        from .fsutil import protect_inputs
        from .segment.check import CLI_PROMPT_TIP, overlay_caption
        from .segment.overlay import mask_overlay, with_caption, write_overlay

        picture = mask_overlay(seg.image, seg.mask, seg.background, object_points=obj_pts, background_points=bg_pts,
                               box=box, force_points=force_pts)
        with protect_inputs(image if isinstance(image, (str, Path)) else None):
            write_overlay(overlay_path, with_caption(picture, overlay_caption(mask_report, prompted=given,
                                                                              tip=CLI_PROMPT_TIP)))
    say(f"mask ({stages['segment']}): " + "; ".join(mask_report.summary_lines()))
    unused = unused_prompts_line(stages["segment"], box=box, object_points=obj_pts, background_points=bg_pts)
    if unused:
        say(unused)
    elif box_note:
        say(box_note)
    if overlay_path is not None:
        say(f"mask overlay: {overlay_path}")
    enforce_plausible(mask_report, prompted=given, overlay=overlay_path, how_to_fix=CLI_HOW_TO_FIX,
                      hint="" if stages["segment"] in ("alpha", "mask") else
                      retry_hint(points=bool(obj_pts), box=box is not None, model=stages["segment"] == "sam"))
    if not given:
        # Without weights the automatic pick is a guess that passes the checks above on most wrong
        # objects but not all (docs/quality.md): always say so, and where to look.
        where = (f"look at {overlay_path}" if overlay_path is not None
                 else "look at it first with `physmotion segment IMAGE -o overlay.png`")
        text = (f"the object was picked automatically ({stages['segment']}, no point, box or mask given): {where}. "
                "If it is not the object you mean, give --object-point U,V or --box X0,Y0,X1,Y1.")
        say(text, warn=True)

    # What holds it up: the ground, or the frame's edge where the photo cuts it off.
    from .support import plan_support

    user_ground = conditions.ground()
    support = plan_support(seg.mask, ground=user_ground, object_height=float(object_height),
                           hold_edges=bool(hold_edges) and mat.model != "rigid", height_given=height_given)
    if hold_edges and mat.model == "rigid" and support.edges:
        support.lines.insert(0, "support: the photo cuts the object at the frame's edge, but a rigid object is not "
                                "held there (a held rigid body could not move at all); it rests on the ground.")
    for line in support.lines:
        say(line)
    if support.ground is not user_ground:
        conditions = Conditions([c for c in conditions if not isinstance(c, Ground)] + [support.ground])

    t = time.perf_counter()
    if found["lgm"] and found["imagedream"]:
        from .lift.imagedream import load_imagedream
        from .lift.learned import learned_lift
        from .lift.lgm import load_lgm

        log.info("lifting with ImageDream (%s) + LGM (%s)", found["imagedream"], found["lgm"])
        dtype = default_dtype(device)
        lgm = load_lgm(found["lgm"], device=device, dtype=dtype, input_size=int(lgm_input_size))
        dream = load_imagedream(found["imagedream"], device=device, dtype=dtype)
        lift = learned_lift(rgb, seg.mask, lgm=lgm, imagedream=dream, object_height=object_height,
                            on_ground=user_ground is not None,
                            ground_height=user_ground.height if user_ground is not None else 0.0,
                            seed=int(seed), steps=int(multiview_steps), max_gaussians=int(max_gaussians),
                            progress=stage("lift"))
        del lgm, dream
        stages["lift"] = "lgm"
    else:
        if models == "auto" and (found["lgm"] or found["imagedream"]):
            log.warning("the learned lift needs both LGM and ImageDream weights (found only %s): using the "
                        "silhouette lift", "LGM" if found["lgm"] else "ImageDream")
        lift = silhouette_lift(seg.image, seg.mask, object_height=object_height, fov_y_deg=fov_y_deg,
                               max_gaussians=max_gaussians, on_ground=user_ground is not None,
                               ground_height=user_ground.height if user_ground is not None else 0.0)
        stages["lift"] = "silhouette"
        if lift.info.get("ball"):
            say("lift: the outline is round, its bottom too: lifted as a ball, as deep as it is wide (so it rolls).")
    timings["lift_s"] = time.perf_counter() - t
    if support.anchor is not None:
        from .support import anchor_reaches

        if anchor_reaches(support.anchor, lift.gaussians, lift.camera):
            conditions = conditions + support.anchor
        else:
            support.anchor, support.hold = None, False
            say("support: the lifted object does not reach the frame's edge where the mask does, so nothing is "
                "held there; it rests on the ground.", warn=True)
    prep = Prepared(segmentation=seg, mask_report=mask_report, support=support, gaussians=lift.gaussians,
                    camera=lift.camera, material=mat, conditions=conditions, settings=settings, stages=stages,
                    lines=lines, overlay_path=overlay_path, lift=lift, timings=timings)
    prep._say = say  # the same reporter for what generate says later
    if _weigh:
        from .feedback import body_facts, forecast
        from .sim.mpm import resolve_device

        facts = body_facts(lift.gaussians, mat, settings, conditions.ground(), resolve_device(settings.device))
        prep.mass_kg = facts.total_mass
        for line in forecast(conditions, facts, mat, clip_s=(settings.frames - 1) / settings.fps,
                             camera=lift.camera, held=support.anchor is not None, cfl=settings.cfl,
                             held_edges=support.edges):
            say(line)
    return prep


def generate(
    image: Union[str, Path, torch.Tensor, np.ndarray],
    *,
    conditions: Conditions | None = None,
    material: Union[str, Material] = "jelly",
    material_params: Optional[dict] = None,
    mask: Optional[torch.Tensor] = None,
    ground: Optional[Ground] = Ground(0.0, "friction", 0.5),
    object_height: Optional[float] = None,
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
    object_points=(),
    background_points=(),
    box: Optional[tuple[float, float, float, float]] = None,
    hold_edges: bool = True,
    overlay: Union[str, Path, None] = None,
    report: Optional[Callable[[str], None]] = None,
    preview: bool = False,
    texture: str = "photo",
):
    """Animate the object in ``image`` under ``conditions`` and return (and optionally save) the video.

    ``ground`` is added to the conditions unless they already contain a Ground; pass None for no
    ground (the object then falls out of the domain floor's reach only as far as its walls allow).

    ``max_side``: a photo whose long side is larger is scaled down to it first (logged), with its
    alpha and mask, and pixel regions (``Region.at_pixel``) refer to the scaled image; 0 keeps the
    full size. The clip's memory is checked before the simulation starts.

    Which object: an alpha channel or ``mask`` is taken as given. Otherwise ``object_points`` /
    ``background_points`` ((u, v) pixels of the photo as given; ``object_point`` is one more object
    point) and ``box`` (x0, y0, x1, y1 pixels) prompt SAM when its weights are in the models root
    (``models="auto"``), else GrabCut; with no prompt SAM's most salient object, else GrabCut around
    the automatic box. Every mask is checked (``segment.check.check_mask``: frame edges touched, area,
    separate parts, missed points); an automatic one that fails is refused with a message naming the
    overlay (``overlay``, default ``<output>.mask.png``) and how to give a point, a box or a mask; a
    prompted or given one only warns.

    ``texture``: "photo" (default) renders the surface the photo saw with the photo's own pixels, carried
    by the motion (``render.photo_texture``); "splat" renders the Gaussians' colours only.

    What holds it: the parts the frame's edge cuts are held there (``hold_edges``), and the ground
    goes under the lowest visible point unless that is on the frame's edge (``support.plan_support``).
    ``object_height`` (metres, default 0.3, said to be assumed) sets the object's real size.

    Before the simulation the mass, material and what each load will roughly do are told through
    ``report`` (a callable taking one line; default: the log), and after it a warning when nothing
    moved or the object left the frame. ``preview=True`` stops before simulating and returns the
    ``Prepared`` state (mask report, support, mass, lines).

    ``models="auto"`` uses the learned stages whose weights are in the models root and skips what
    the scene does not need. LGM + ImageDream both present → the learned lift (``seed``,
    ``multiview_steps``, ``lgm_input_size``), else the silhouette lift. ``"none"`` never loads a
    model. ``result.stages`` says which path each stage took.
    """
    from .render.frames import render_frames
    from .sim import simulate

    def stage(name: str) -> Optional[ProgressFn]:
        return progress(name) if progress is not None else None

    if texture not in ("photo", "splat"):
        raise InputError(f"texture must be 'photo' (the photo's own pixels move) or 'splat' (the Gaussians' "
                         f"colours); got {texture!r}")
    t0 = time.perf_counter()
    prep = prepare(image, conditions=conditions, material=material, material_params=material_params, mask=mask,
                   ground=ground, object_height=object_height, fov_y_deg=fov_y_deg, max_gaussians=max_gaussians,
                   settings=settings, output=output, progress=progress, max_side=max_side, models=models, seed=seed,
                   multiview_steps=multiview_steps, lgm_input_size=lgm_input_size, object_point=object_point,
                   object_points=object_points, background_points=background_points, box=box,
                   hold_edges=hold_edges, overlay=overlay, report=report, _weigh=preview)
    if preview:
        prep.timings["total_s"] = time.perf_counter() - t0
        return prep
    say = prep._say
    seg, settings, conditions, mat = prep.segmentation, prep.settings, prep.conditions, prep.material
    timings = prep.timings
    lift = prep.lift

    def told(facts) -> None:
        from .feedback import forecast

        prep.mass_kg = facts.total_mass
        for line in forecast(conditions, facts, mat, clip_s=(settings.frames - 1) / settings.fps,
                             camera=lift.camera, held=prep.support.anchor is not None, cfl=settings.cfl,
                             held_edges=prep.support.edges):
            say(line)

    t = time.perf_counter()
    sim = simulate(lift.gaussians, mat, conditions, settings, camera=lift.camera, progress=stage("simulate"),
                   on_start=told)
    timings["simulate_s"] = time.perf_counter() - t
    from .feedback import after_run

    motion = after_run(sim, lift.camera)
    for w in motion.warnings:
        say(w, warn=True)

    t = time.perf_counter()
    texture_map = None
    if texture == "photo":
        from .render.photo_texture import make_photo_texture

        # The photo itself moves (the surface it saw keeps its pixels); the soft matte where the
        # segmentation has one.
        matte = getattr(seg, "matte", None)
        texture_map = make_photo_texture(seg.image, seg.mask if matte is None else matte, lift.camera,
                                         background=seg.background)
    frames = render_frames(sim, lift.camera, progress=stage("render"), photo=texture_map)
    timings["render_s"] = time.perf_counter() - t

    video = composite(frames.rgb, frames.alpha, seg.background)
    result = PipelineResult(frames=video, fps=settings.fps, segmentation=seg, gaussians=lift.gaussians,
                            camera=lift.camera, sim=sim, render=frames, timings=timings, stages=prep.stages,
                            notes=list(prep.lines), mask_report=prep.mask_report, support=prep.support,
                            motion=motion)
    if output is not None:
        from .fsutil import protect_inputs
        from .video import write_mp4

        t = time.perf_counter()
        with protect_inputs(image if isinstance(image, (str, Path)) else None):
            result.video_path = write_mp4(output, video, fps=settings.fps)
        timings["encode_s"] = time.perf_counter() - t
    timings["total_s"] = time.perf_counter() - t0
    return result
