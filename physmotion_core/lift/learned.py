"""The learned lift: photo + object mask → ImageDream's 4 views → LGM's Gaussians, in our world.

What the original (LGM ``infer.py``) does around the networks, and what we add to put its result
into the scene:

1. **Recentre** (``recenter``): the object, composited on white with its mask, is cropped to its
   bounding box and scaled so that its longer side fills ``1 - border_ratio`` of a square canvas
   (border 0.2 as the original), centred. The map photo → canvas is a per-axis scale and shift
   (``RecenterMap``), kept to build the input camera later. (kiui's ``recenter`` drops the last row
   and column of the box; we keep the whole box.)
2. **Views**: ImageDream generates 4 views of the canvas (``generate_views``); ``views_for_lgm``
   orders them as LGM's cameras: azimuth 0 (the input side), 90, 180, 270 degrees.
3. **LGM input** (``lgm_input``): views bilinearly resized to ``input_size``, ImageNet-normalised,
   concatenated with the Plücker rays of LGM's 4 cameras → ``[1, 4, 9, S, S]``.
4. **LGM** forward + activations (``lgm.py``), then **pruning** of near-transparent Gaussians
   (opacity < 0.005, as the original's ``save_ply``), optionally capped at ``max_gaussians``
   (the most opaque are kept).
5. **Into our world** (``lgm_gaussians_to_world``). LGM's frame already has our axes (+y up, the
   input camera on +z looking down -z, OpenGL); its unit is arbitrary (the object within
   [-1, 1]³, cameras at radius 1.5). A similarity x_world = s · x_lgm + (0, t_y, 0) with s =
   ``object_height`` / (height of the Gaussian centres) and t_y putting the lowest centre on
   ``ground_height`` (``on_ground``; otherwise the object is centred on that height) gives metres.
   Quaternions are unchanged (no rotation); scales are multiplied by s. For weights with the
   dim-1 rotation quirk the covariance is rebuilt the way the original rasterizer saw it (see
   ``lgm.py``) and decomposed into a unit quaternion and scales.
6. **The input camera** (``input_camera``). LGM's azimuth-0 camera (fovy 49.1°, radius 1.5,
   square canvas) sees the canvas; the canvas is the photo under the per-axis similarity of step
   1, and a similarity of the image plane is a change of intrinsics. So the photo's camera has
   LGM's azimuth-0 pose (moved by the world similarity, which leaves images unchanged) and
   ``fx = f_c / s_x``, ``fy = f_c / s_y``, ``cx = (c_c - x_canvas0) / s_x + x_photo0`` (same for y),
   with f_c, c_c the canvas intrinsics. Rendering the lifted Gaussians through it gives exactly
   LGM's own azimuth-0 render, mapped back from the canvas onto the photo: where LGM reproduces
   its input view, the render lands on the input mask. (A shift-lens camera: the object is seen
   from straight ahead wherever it is in the frame, as LGM assumes.)
7. **Views for refinement**: each generated view with its camera (LGM's camera of that azimuth,
   moved into our world), its object mask (the non-white pixels, cleaned) and the object over
   black, as ``RefineView`` records for the Hard-Depth Refine stage (depth targets only: their
   colours are generated, not observed).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InputError
from ..progress import ProgressFn, report, scaled
from ..refine.refine import RefineView
from ..segment.classic import as_image_array, as_mask_array, clean_mask
from ..types.camera import Camera
from ..types.gaussians import Gaussians, rotmat_to_quat
from .lgm import (IMAGENET_MEAN, IMAGENET_STD, LGM_AZIMUTHS, NUM_VIEWS, LGMNet, default_rays, orbit_pose,
                  raw_rotation_matrix)
from .silhouette import MIN_MASK_PIXELS, LiftResult

log = logging.getLogger(__name__)

__all__ = ["RecenterMap", "recenter", "lgm_input", "run_lgm", "lgm_gaussians_to_world", "input_camera",
           "view_mask", "generated_views", "learned_lift", "LearnedLiftResult", "PRUNE_OPACITY",
           "BORDER_RATIO", "views_for_refine"]

PRUNE_OPACITY = 0.005          # the original's save_ply threshold
BORDER_RATIO = 0.2             # the original's recenter border
WHITE_THRESHOLD = 0.06         # a generated view's pixel is background when every channel is within this of 1


# ----------------------------------------------------------------------------------------------
# 1. recentring
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class RecenterMap:
    """canvas = (photo - photo_origin) * scale + canvas_origin, per axis, in continuous pixel
    coordinates (pixel i spans [i, i+1], its centre is i + 0.5)."""

    canvas_size: int
    photo_width: int
    photo_height: int
    photo_x0: float
    photo_y0: float
    canvas_x0: float
    canvas_y0: float
    scale_x: float
    scale_y: float

    def to_canvas(self, uv: torch.Tensor) -> torch.Tensor:
        s = torch.tensor([self.scale_x, self.scale_y], dtype=uv.dtype, device=uv.device)
        o = torch.tensor([self.photo_x0, self.photo_y0], dtype=uv.dtype, device=uv.device)
        c = torch.tensor([self.canvas_x0, self.canvas_y0], dtype=uv.dtype, device=uv.device)
        return (uv - o) * s + c

    def to_photo(self, uv: torch.Tensor) -> torch.Tensor:
        s = torch.tensor([self.scale_x, self.scale_y], dtype=uv.dtype, device=uv.device)
        o = torch.tensor([self.photo_x0, self.photo_y0], dtype=uv.dtype, device=uv.device)
        c = torch.tensor([self.canvas_x0, self.canvas_y0], dtype=uv.dtype, device=uv.device)
        return (uv - c) / s + o


def _check_border(border_ratio) -> float:
    try:
        b = float(border_ratio)
    except (TypeError, ValueError):
        b = float("nan")
    if not (0.0 <= b < 0.9):
        raise InputError(f"border_ratio must be in [0, 0.9) (0.2 as LGM: the object fills 80 % of the views); "
                         f"got {border_ratio!r}")
    return b


def recenter(image, mask, *, border_ratio: float = BORDER_RATIO, size: int = 256):
    """The object on white, centred in a ``size`` x ``size`` canvas with its longer side filling
    ``1 - border_ratio`` of it. Returns (canvas [S,S,3] float32 0..1, canvas mask [S,S] float32,
    ``RecenterMap``)."""
    img = as_image_array(image)
    H, W = img.shape[:2]
    if mask is None:
        raise InputError("The learned lift needs the object mask (H, W); segment the image first")
    m = as_mask_array(mask, (H, W)).clip(0, 1)
    b = _check_border(border_ratio)
    size = int(size)
    if size < 16:
        raise InputError(f"recenter: the canvas must be at least 16 px; got {size}")
    on = m > 0.5
    n_px = int(on.sum())
    if n_px < MIN_MASK_PIXELS:
        raise InputError(f"The object mask has {n_px} pixels; the lift needs at least {MIN_MASK_PIXELS}. "
                         "Check the segmentation (the mask may be empty or the object tiny).")
    ys, xs = np.nonzero(on)
    x0, x1, y0, y1 = int(xs.min()), int(xs.max()) + 1, int(ys.min()), int(ys.max()) + 1
    w, h = x1 - x0, y1 - y0
    scale = max(1, int(size * (1.0 - b))) / max(w, h)
    w2, h2 = max(1, int(round(w * scale))), max(1, int(round(h * scale)))
    cx0, cy0 = (size - w2) // 2, (size - h2) // 2
    on_white = img * m[..., None] + (1.0 - m[..., None])
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    canvas = np.ones((size, size, 3), np.float32)
    canvas[cy0:cy0 + h2, cx0:cx0 + w2] = cv2.resize(on_white[y0:y1, x0:x1], (w2, h2), interpolation=interp)
    cmask = np.zeros((size, size), np.float32)
    cmask[cy0:cy0 + h2, cx0:cx0 + w2] = cv2.resize(np.ascontiguousarray(m[y0:y1, x0:x1]), (w2, h2),
                                                   interpolation=interp)
    rmap = RecenterMap(canvas_size=size, photo_width=W, photo_height=H, photo_x0=float(x0), photo_y0=float(y0),
                       canvas_x0=float(cx0), canvas_y0=float(cy0), scale_x=w2 / w, scale_y=h2 / h)
    return np.clip(canvas, 0, 1), np.clip(cmask, 0, 1), rmap


# ----------------------------------------------------------------------------------------------
# 3-4. LGM input and forward
# ----------------------------------------------------------------------------------------------

def _as_views(views) -> torch.Tensor:
    v = torch.as_tensor(np.asarray(views) if not isinstance(views, torch.Tensor) else views).float()
    if v.ndim != 4 or v.shape[0] != NUM_VIEWS or v.shape[-1] != 3 or v.shape[1] != v.shape[2]:
        raise InputError(f"The views must be {NUM_VIEWS} square RGB images [4, S, S, 3] in LGM's order (azimuth "
                         f"0, 90, 180, 270; Multi-View Generate's output); got shape {tuple(v.shape)}")
    if not bool(torch.isfinite(v).all()) or float(v.min()) < -1e-3 or float(v.max()) > 1 + 1e-3:
        raise InputError("The views must be finite RGB values in 0..1")
    return v.clamp(0, 1).cpu()


def lgm_input(views, lgm: LGMNet, elevation: float = 0.0) -> torch.Tensor:
    """``[1, 4, 9, S, S]`` (S = the LGM's input size): views (LGM order, [4, s, s, 3] in 0..1)
    resized bilinearly, ImageNet-normalised, with the Plücker rays of LGM's cameras appended."""
    v = _as_views(views).permute(0, 3, 1, 2)
    size = lgm.cfg.input_size
    v = F.interpolate(v, size=(size, size), mode="bilinear", align_corners=False)
    mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    v = (v - mean) / std
    return torch.cat([v, default_rays(lgm.cfg, elevation)], dim=1)[None]


@torch.no_grad()
def run_lgm(lgm: LGMNet, views) -> torch.Tensor:
    """Activated Gaussians ``[N, 14]`` float32 (LGM's frame and layout) for one object's 4 views."""
    x = lgm_input(views, lgm).to(device=lgm.device, dtype=lgm.dtype)
    if lgm.device.type == "cuda" and lgm.dtype == torch.float16:
        with torch.autocast("cuda", dtype=torch.float16):     # as infer.py
            out = lgm.forward_gaussians(x)
    else:
        out = lgm.forward_gaussians(x)
    return out[0].float().cpu()


# ----------------------------------------------------------------------------------------------
# 5-6. world frame and input camera
# ----------------------------------------------------------------------------------------------

def _canvas_intrinsics(size: int, fovy_deg: float) -> tuple[float, float]:
    return 0.5 * size / math.tan(0.5 * math.radians(fovy_deg)), 0.5 * size


def _world_pose(c2w_lgm: torch.Tensor, scale: float, shift: torch.Tensor) -> torch.Tensor:
    c2w = c2w_lgm.clone()
    c2w[:3, 3] = c2w[:3, 3] * scale + shift
    return c2w


def _clip_planes(distance: float) -> dict:
    return {"near": min(0.01, 0.05 * distance), "far": max(100.0, 20.0 * distance)}


def input_camera(rmap: RecenterMap, scale: float, shift: torch.Tensor, *, fovy_deg: float = 49.1,
                 radius: float = 1.5) -> Camera:
    """The camera through which the world Gaussians reproduce the photo (module docstring, step 6)."""
    f_c, c_c = _canvas_intrinsics(rmap.canvas_size, fovy_deg)
    fx, fy = f_c / rmap.scale_x, f_c / rmap.scale_y
    cx = (c_c - rmap.canvas_x0) / rmap.scale_x + rmap.photo_x0
    cy = (c_c - rmap.canvas_y0) / rmap.scale_y + rmap.photo_y0
    c2w = _world_pose(orbit_pose(0.0, 0.0, radius), scale, shift)
    return Camera(rmap.photo_width, rmap.photo_height, fx, fy, cx, cy, c2w, **_clip_planes(radius * scale))


def lgm_gaussians_to_world(g_lgm: torch.Tensor, *, rotation_dim: int, object_height: float = 0.3,
                           on_ground: bool = True, ground_height: float = 0.0):
    """LGM's activated ``[N, 14]`` → (Gaussians in metres, scale s, shift (3,)). See step 5."""
    if g_lgm.ndim != 2 or g_lgm.shape[1] != 14 or g_lgm.shape[0] == 0:
        raise InputError(f"LGM Gaussians must be a non-empty [N, 14]; got {tuple(g_lgm.shape)}")
    g = g_lgm.float()
    pos, opacity, scales, quats, rgb = g[:, 0:3], g[:, 3], g[:, 4:7], g[:, 7:11], g[:, 11:14]
    y = pos[:, 1]
    height = float(y.max() - y.min())
    if not height > 1e-6:
        raise InputError("LGM's Gaussians have no vertical extent (all at one height); the lift failed. Check "
                         "the mask and the generated views.")
    s = float(object_height) / height
    ty = float(ground_height) - s * (float(y.min()) if on_ground else 0.5 * float(y.min() + y.max()))
    shift = torch.tensor([0.0, ty, 0.0])
    if rotation_dim == 1:
        # The original weights' quaternions are not unit: rebuild the covariance the original
        # rasterizer drew from them, R(q) S² R(q)ᵀ, and decompose it (eigenvectors = axes).
        R = raw_rotation_matrix(quats.double())
        M = R * scales.double()[:, None, :]
        cov = M @ M.transpose(1, 2)
        evals, evecs = torch.linalg.eigh(0.5 * (cov + cov.transpose(1, 2)))
        evecs = evecs * torch.sign(torch.linalg.det(evecs))[:, None, None]
        scales = evals.clamp_min(1e-24).sqrt().float()
        quats = rotmat_to_quat(evecs).float()
    else:
        quats = F.normalize(quats, dim=-1)
    gaussians = Gaussians.from_rgb(pos * s + shift, rgb.clamp(0, 1), (scales * s).clamp_min(1e-12),
                                   opacity.clamp(0, 1), quats)
    return gaussians, s, shift


# ----------------------------------------------------------------------------------------------
# 7. generated views as refinement targets
# ----------------------------------------------------------------------------------------------

def view_mask(view: torch.Tensor, threshold: float = WHITE_THRESHOLD) -> torch.Tensor:
    """Object mask of a generated view on white: some channel darker than 1 - threshold, cleaned
    (specks dropped, small holes filled)."""
    m = ((1.0 - view.float()).amax(dim=-1) > threshold).float()
    return clean_mask(m)


def generated_views(view_images: torch.Tensor, scale: float, shift: torch.Tensor, *, fovy_deg: float = 49.1,
                    radius: float = 1.5) -> list:
    """``RefineView`` records (camera in our world, object over black, mask) for LGM-ordered views."""
    out = []
    size = int(view_images.shape[1])
    f, c = _canvas_intrinsics(size, fovy_deg)
    for k, az in enumerate(LGM_AZIMUTHS):
        img = view_images[k].float().cpu()
        m = view_mask(img)
        cam = Camera(size, size, f, f, c, c, _world_pose(orbit_pose(0.0, az, radius), scale, shift),
                     **_clip_planes(radius * scale))
        out.append(RefineView(camera=cam, image=img * m[..., None], mask=m, colour=False,
                              name=f"imagedream_az{int(az):03d}"))
    return out


def views_for_refine(views: Sequence[RefineView], include_front: bool = False) -> list:
    """The generated views to refine against: by default without the azimuth-0 one, whose
    direction the real photo already covers (its generated mask would prune real Gaussians), and
    never a view in which no object was found (an all-white view has nothing to compare)."""
    out = []
    for v in views:
        if not include_front and v.name.endswith("az000"):
            continue
        if v.mask is not None and not bool((v.mask > 0.5).any()):
            log.warning("learned lift: generated view %s shows no object; it is left out of refinement", v.name)
            continue
        out.append(v)
    return out


# ----------------------------------------------------------------------------------------------
# the whole lift
# ----------------------------------------------------------------------------------------------

@dataclass
class LearnedLiftResult(LiftResult):
    """``LiftResult`` plus what the learned lift saw: ``view_images`` [4, S, S, 3] (LGM order:
    azimuth 0, 90, 180, 270), ``views`` (``RefineView`` per generated view, cameras in our world),
    ``canvas`` (the recentred input), ``recenter_map``, ``lgm_gaussians`` (the kept Gaussians in
    LGM's frame and layout, [N, 14]), the world similarity (``scale``, ``shift``) and
    ``source_view`` (N,) which view's splat grid each Gaussian came from (``source_px``: its
    (x, y) in that grid)."""

    view_images: Optional[torch.Tensor] = None
    views: list = field(default_factory=list)
    canvas: Optional[torch.Tensor] = None
    recenter_map: Optional[RecenterMap] = None
    lgm_gaussians: Optional[torch.Tensor] = None
    scale: float = 1.0
    shift: Optional[torch.Tensor] = None
    source_view: Optional[torch.Tensor] = None


def _positive(name, value, lo=0.0, hi=math.inf, what="a positive number") -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = float("nan")
    if not (math.isfinite(v) and lo < v <= hi):
        raise InputError(f"learned_lift: {name} must be {what}; got {value!r}")
    return v


def learned_lift(image, mask, *, lgm: LGMNet, imagedream=None, views=None, object_height: float = 0.3,
                 on_ground: bool = True, ground_height: float = 0.0, border_ratio: float = BORDER_RATIO,
                 seed: int = 0, steps: int = 30, guidance_scale: float = 5.0, prompt: str = "",
                 prune_opacity: float = PRUNE_OPACITY, max_gaussians: int = 0,
                 progress: Optional[ProgressFn] = None,
                 cancel: Optional[Callable[[], None]] = None) -> LearnedLiftResult:
    """Lift the masked object of ``image`` with ImageDream + LGM (module docstring).

    ``imagedream``: an ``ImageDreamPipeline`` to generate the views; or ``views``: 4 views already
    generated from this image, mask and ``border_ratio`` ([4, S, S, 3] in LGM order, e.g. from
    ``generate_views`` + ``views_for_lgm`` on ``recenter``'s canvas). ``object_height`` (metres)
    scales the result; ``on_ground`` puts its lowest Gaussian centre on ``ground_height``.
    ``prune_opacity``: Gaussians less opaque are dropped; ``max_gaussians`` > 0 keeps only the
    most opaque ones. ``progress(done, total)`` runs over the ImageDream steps + 1 for LGM;
    ``cancel()`` is called before every step (either may raise to stop). Models run where they are
    (move them to the GPU first).
    """
    t0 = time.perf_counter()
    object_height = _positive("object_height", object_height, what="a positive number of metres (0.3 for a mug)")
    try:
        prune_opacity = float(prune_opacity)
    except (TypeError, ValueError):
        prune_opacity = float("nan")
    if not 0.0 <= prune_opacity < 1.0:
        raise InputError(f"learned_lift: prune_opacity must be in [0, 1) (0.005 as LGM); got {prune_opacity!r}")
    if not math.isfinite(float(ground_height)):
        raise InputError(f"learned_lift: ground_height must be a finite height in metres; got {ground_height!r}")
    if isinstance(max_gaussians, bool) or int(max_gaussians) < 0:
        raise InputError(f"learned_lift: max_gaussians must be >= 0 (0 = no cap); got {max_gaussians!r}")
    if imagedream is None and views is None:
        raise InputError("learned_lift needs an ImageDream pipeline (imagedream=) or 4 generated views (views=)")
    img = as_image_array(image)
    H, W = img.shape[:2]
    m = as_mask_array(mask, (H, W)) if mask is not None else None
    if views is not None:
        view_images = _as_views(views)
        size = int(view_images.shape[1])
    else:
        size = int(imagedream.image_size)
    canvas, cmask, rmap = recenter(img, m, border_ratio=border_ratio, size=size)

    total = (0 if views is not None else int(steps)) + 1
    if views is None:
        from .imagedream import generate_views, views_for_lgm

        raw_views = generate_views(imagedream, canvas, prompt=prompt, guidance_scale=guidance_scale,
                                   num_inference_steps=steps, elevation=0.0, seed=seed,
                                   progress=scaled(progress, 0, total - 1, total), cancel=cancel)
        view_images = views_for_lgm(raw_views).float().cpu()
    if cancel is not None:
        cancel()
    g_all = run_lgm(lgm, view_images)
    report(progress, total, total)

    n_all = g_all.shape[0]
    splat = lgm.cfg.splat_size
    idx = torch.arange(n_all)
    keep = g_all[:, 3] >= float(prune_opacity)
    if not bool(keep.any()):
        raise InputError(f"Every one of LGM's {n_all} Gaussians is below the opacity threshold {prune_opacity}; "
                         "lower prune_opacity or check the generated views (they should show the object on white).")
    idx = idx[keep]
    if max_gaussians and len(idx) > int(max_gaussians):
        order = torch.argsort(g_all[idx, 3], descending=True, stable=True)[: int(max_gaussians)]
        idx = idx[order.sort().values]
    g_kept = g_all[idx]
    gaussians, s, shift = lgm_gaussians_to_world(g_kept, rotation_dim=lgm.rotation_dim,
                                                 object_height=object_height, on_ground=bool(on_ground),
                                                 ground_height=float(ground_height))
    gaussians.validate("LGM lift Gaussians")
    camera = input_camera(rmap, s, shift, fovy_deg=lgm.cfg.fovy, radius=lgm.cfg.cam_radius)
    refine_views = generated_views(view_images, s, shift, fovy_deg=lgm.cfg.fovy, radius=lgm.cfg.cam_radius)
    per_view = splat * splat
    source_view = (idx // per_view).to(torch.int64)
    within = idx % per_view
    source_px = torch.stack([within % splat, within // splat], dim=-1).to(torch.int64)
    info = {"n_lgm": n_all, "n_kept": len(idx), "n_pruned": n_all - len(idx), "scale": s,
            "y_shift": float(shift[1]), "splat_size": splat, "input_size": lgm.cfg.input_size,
            "rotation_dim": lgm.rotation_dim, "view_size": size, "border_ratio": float(border_ratio),
            "distance": lgm.cfg.cam_radius * s, "seconds": time.perf_counter() - t0}
    log.info("learned lift: %d of %d Gaussians kept, %.3f m per LGM unit, %.1f s", len(idx), n_all, s,
             info["seconds"])
    return LearnedLiftResult(gaussians=gaussians, camera=camera, mask=torch.from_numpy((m > 0.5).astype(np.float32)),
                             layer=None, source_px=source_px, info=info, view_images=view_images,
                             views=refine_views, canvas=torch.from_numpy(canvas), recenter_map=rmap,
                             lgm_gaussians=g_kept, scale=s, shift=shift, source_view=source_view)
