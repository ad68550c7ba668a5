"""Controls for ComfyUI's Wan video models, taken from the simulation: point tracks, control videos
and exact optical flow.

The simulator knows where every point of the object goes, so it can hand a video model better
controls than any estimator run on the coarse video:

* ``point_tracks`` + ``wan_tracks_json``: the ``tracks`` STRING of ComfyUI's ``WanTrackToVideo``
  (ATI). Points spread evenly over the object's visible silhouette in frame 0 follow the physics
  particles under them, projected through the photo's camera; a point's visibility per frame comes
  from the rendered depth.
* ``control_videos``: depth (near = bright), the coarse render, the object mask, the blended coarse
  video and a VACE control (depth inside the mask, the coarse video outside) for
  ``WanVaceToVideo`` / ``Wan22FunControlToVideo``.
* ``exact_flow``: forward (or backward) optical flow per frame pair from the splats behind each
  visible pixel, with ``flow_to_color`` (colour-wheel preview) and ``save_flow_npz``.

Everything runs at the video model's clock: ``resample_simulation`` interpolates the simulated
frames to ``fps`` (Wan: 16) and a 4k+1 frame count, and ``fit_camera`` / ``fit_images`` crop and
scale exactly as ``comfy.utils.common_upscale(..., "center")`` does inside the Wan nodes, so the
controls line up with the photo the Wan node receives as its start/reference image.

The ``tracks`` format is matched to ComfyUI 0.3.64, commit 637221995f7424a561bd825de3e61ea117dfe1e3
(``comfy_extras/nodes_wan.py``: ``parse_json_tracks``, ``pad_pts``, ``process_tracks``,
``WanTrackToVideo``), read there, not copied:

* the STRING is a JSON list of tracks, each a list of ``{"x": .., "y": ..}`` points, in pixels of
  the ``width`` x ``height`` frame the node is given (x right, y down, origin at the top-left corner;
  the node subtracts (width/2, height/2) and divides by min(width, height)/2);
* each track holds up to 121 samples (``FIXED_LENGTH``) spanning the whole clip: sample 0 is frame 0
  and output frame j (1..length-1) reads sample ``1 + (1 + a (j-1)) // b`` with
  ``a = 120 / gcd(120, length-1)``, ``b = (length-1) / gcd(120, length-1)``;
* there is no visibility field: ``pad_pts`` gives every listed point visibility 1 and pads a shorter
  track with invisible points. So a point that becomes hidden (behind the object, or off-screen)
  ends its track at the first sample that shows it hidden (``occlusion="end"``), which the model
  reads as "invisible from here on"; ``occlusion="keep"`` lists all 121 samples regardless.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import numbers
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from .errors import InputError
from .progress import ProgressFn, report
from .types.camera import Camera
from .types.results import FrameSet, SimResult

log = logging.getLogger(__name__)

#: The frame rate Wan 2.1 / 2.2 models are trained at.
WAN_FPS = 16.0
#: Samples per track that WanTrackToVideo reads (``FIXED_LENGTH`` in nodes_wan.py at 0.3.64).
WAN_TRACK_SAMPLES = 121
#: The commit of ComfyUI whose Wan nodes these controls are matched to (tag v0.3.64).
COMFYUI_COMMIT = "637221995f7424a561bd825de3e61ea117dfe1e3"


# ----------------------------------------------------------------------------------------------
# Sizes and cameras
# ----------------------------------------------------------------------------------------------


def check_size(width: int, height: int, multiple: int = 16) -> tuple[int, int]:
    w, h = int(width), int(height)
    if w < multiple or h < multiple or w % multiple or h % multiple:
        raise InputError(f"The control size must be a multiple of {multiple} pixels in both directions (Wan's "
                         f"VAE and patch size); got {w}x{h}. Use e.g. 832x480 or 480x832.")
    return w, h


def center_crop_box(src_w: int, src_h: int, dst_w: int, dst_h: int) -> tuple[int, int, int, int]:
    """(x, y, w, h) of the centred crop ``comfy.utils.common_upscale(..., crop="center")`` takes from
    a src_w x src_h image before scaling it to dst_w x dst_h (the same rounding)."""
    old_aspect, new_aspect = src_w / src_h, dst_w / dst_h
    x = y = 0
    if old_aspect > new_aspect:
        x = round((src_w - src_w * (new_aspect / old_aspect)) / 2)
    elif old_aspect < new_aspect:
        y = round((src_h - src_h * (old_aspect / new_aspect)) / 2)
    return x, y, src_w - 2 * x, src_h - 2 * y


def fit_camera(camera: Camera, width: int, height: int) -> Camera:
    """The camera whose image is the photo centre-cropped to width:height and scaled to width x height
    (what the Wan nodes do to their start/reference image), so renders line up with it."""
    x, y, w, h = center_crop_box(camera.width, camera.height, int(width), int(height))
    sx, sy = width / w, height / h
    return dataclasses.replace(camera, width=int(width), height=int(height), fx=camera.fx * sx, fy=camera.fy * sy,
                               cx=(camera.cx - x) * sx, cy=(camera.cy - y) * sy, c2w=camera.c2w.clone())


def fit_images(images: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """IMAGE (B,H,W,C) or MASK (B,H,W) batch centre-cropped and bilinearly scaled to width x height,
    as ``comfy.utils.common_upscale(..., "bilinear", "center")``."""
    is_mask = images.ndim == 3
    t = images[..., None] if is_mask else images
    if t.ndim != 4:
        raise InputError(f"Expected an IMAGE [B,H,W,C] or MASK [B,H,W] batch; got shape {tuple(images.shape)}")
    x, y, w, h = center_crop_box(t.shape[2], t.shape[1], int(width), int(height))
    t = t[:, y:y + h, x:x + w].permute(0, 3, 1, 2).float()
    if (h, w) != (height, width):
        t = torch.nn.functional.interpolate(t, size=(int(height), int(width)), mode="bilinear")
    t = t.permute(0, 2, 3, 1)
    return t[..., 0] if is_mask else t


# ----------------------------------------------------------------------------------------------
# Time: the video model's frame rate and 4k+1 frame counts
# ----------------------------------------------------------------------------------------------


def sim_fps(sim: SimResult) -> float:
    return 1.0 / float(sim.times[1] - sim.times[0]) if sim.num_frames > 1 else 24.0


def wan_length(num_frames: int, fps_in: float, fps_out: float = WAN_FPS) -> int:
    """The 4k+1 frame count covering a clip of ``num_frames`` at ``fps_in`` (its duration taken as
    num_frames / fps_in) at ``fps_out``: 48 frames at 24 fps -> 33 frames at 16 fps."""
    for name, value in (("fps_in", fps_in), ("fps_out", fps_out)):
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not (math.isfinite(value)
                                                                                  and 0 < value <= 1000):
            raise InputError(f"wan_length: {name} must be a frame rate in (0, 1000] frames per second; got {value!r}. "
                             "Give the clip's real frame rate (e.g. 24).")
    if isinstance(num_frames, bool) or not isinstance(num_frames, numbers.Integral) or num_frames < 1:
        raise InputError(f"wan_length: num_frames must be a whole number of frames >= 1; got {num_frames!r}")
    k = int(math.floor(num_frames * fps_out / fps_in / 4 + 1e-9))
    return 4 * max(k, 1) + 1


def check_length(length: int) -> int:
    n = int(length)
    if n < 5 or (n - 1) % 4:
        raise InputError(f"Wan models take 4k+1 frames (5, 9, ..., 33, 49, 81); got length={n}. Pick the nearest "
                         f"4k+1 value, e.g. {4 * max(1, round((n - 1) / 4)) + 1}.")
    return n


def resample_plan(num_frames: int, fps_in: float, fps_out: float, length: int):
    """Linear interpolation indices for output frames at t = j / fps_out.

    Returns (i0, i1, w, held): frame j = (1 - w) * in[i0] + w * in[i1]. A time up to one input frame
    past the last simulated frame is extrapolated linearly (48 frames at 24 fps end at 47/24 s, the
    33rd 16 fps frame is at 2.0 s); later ones hold the last frame (``held``)."""
    t_out = np.arange(int(length), dtype=np.float64) / float(fps_out)
    if num_frames == 1:
        z = np.zeros(length, np.int64)
        return z, z, np.zeros(length), t_out > 0
    pos = t_out * float(fps_in)
    held = pos > num_frames - 1 + 1.0 + 1e-9
    i0 = np.minimum(np.floor(pos + 1e-9).astype(np.int64), num_frames - 2)
    w = pos - i0
    i0 = np.where(held, num_frames - 2, i0)
    w = np.where(held, 1.0, w)
    return i0, i0 + 1, w, held


def _lerp(a: torch.Tensor, i0, i1, w) -> torch.Tensor:
    wt = torch.as_tensor(w, dtype=a.dtype).reshape((-1,) + (1,) * (a.ndim - 1))
    return a[torch.as_tensor(i0)] * (1 - wt) + a[torch.as_tensor(i1)] * wt


def resample_simulation(sim: SimResult, fps: float = WAN_FPS, length: int = 0) -> SimResult:
    """The simulation at ``fps`` and ``length`` frames (0 = the 4k+1 count of ``wan_length``).

    Particle positions, deformation gradients and plastic state are interpolated linearly between
    the simulated frames (exact for uniform motion; no overshoot through the ground at an impact, as
    a cubic would have), so every control renders sharp frames at the model's own times instead of
    cross-fading rendered ones."""
    if not (math.isfinite(fps) and 0 < fps <= 1000):
        raise InputError(f"fps must be in (0, 1000]; got {fps}")
    fps_in = sim_fps(sim)
    length = wan_length(sim.num_frames, fps_in, fps) if not length else int(length)
    if length < 1:
        raise InputError(f"length must be at least 1 frame; got {length}")
    i0, i1, w, held = resample_plan(sim.num_frames, fps_in, fps, length)
    if bool(held.any()):
        log.warning("The simulation covers %.3f s but %d frames at %g fps need %.3f s: the last %d frame(s) repeat "
                    "the final simulated state. Simulate more frames to fill them.", sim.num_frames / fps_in,
                    length, fps, (length - 1) / fps, int(held.sum()))
    stats = dict(sim.stats)
    stats["resampled_from"] = {"frames": sim.num_frames, "fps": fps_in, "held_frames": int(held.sum())}
    return dataclasses.replace(
        sim, times=torch.arange(length, dtype=torch.float64) / float(fps),
        x=_lerp(sim.x, i0, i1, w), F=_lerp(sim.F, i0, i1, w),
        plastic=None if sim.plastic is None else _lerp(sim.plastic.float(), i0, i1, w).to(sim.plastic.dtype),
        stats=stats)


def resample_points(values: torch.Tensor, fps_in: float, fps_out: float, length: int) -> torch.Tensor:
    """Any per-frame quantity (T, ...) resampled as ``resample_simulation`` resamples positions."""
    i0, i1, w, _ = resample_plan(values.shape[0], fps_in, fps_out, length)
    return _lerp(values, i0, i1, w)


# ----------------------------------------------------------------------------------------------
# Point tracks
# ----------------------------------------------------------------------------------------------


@dataclass
class Tracks:
    """Image-space tracks: ``uv`` (T,N,2) pixel coordinates (x right, y down, pixel centres at +0.5)
    in a ``width`` x ``height`` frame, ``visible`` (T,N), and the physics particle each object point
    follows (``particle``, -1 for a still background anchor)."""

    uv: torch.Tensor
    visible: torch.Tensor
    particle: torch.Tensor
    width: int
    height: int
    fps: float

    @property
    def num_frames(self) -> int:
        return int(self.uv.shape[0])

    @property
    def num_points(self) -> int:
        return int(self.uv.shape[1])


def sample_even(mask: torch.Tensor, n: int, max_candidates: int = 40_000) -> torch.Tensor:
    """``n`` pixel centres (n,2) spread evenly over a boolean mask (H,W): farthest-point sampling from
    the pixel nearest the mask's centroid (deterministic, no clumps). Fewer when the mask is smaller."""
    ys, xs = torch.nonzero(mask, as_tuple=True)
    if ys.numel() == 0 or n <= 0:
        return torch.zeros(0, 2)
    stride = max(1, int(math.ceil(math.sqrt(ys.numel() / max_candidates))))
    if stride > 1:  # a regular sub-grid of the mask keeps the search small and still even
        keep = (ys % stride == 0) & (xs % stride == 0)
        if bool(keep.any()):
            ys, xs = ys[keep], xs[keep]
    pts = torch.stack([xs, ys], dim=1).double() + 0.5
    n = min(int(n), pts.shape[0])
    centre = pts.mean(0)
    first = int(((pts - centre) ** 2).sum(1).argmin())
    chosen = [first]
    d = ((pts - pts[first]) ** 2).sum(1)
    for _ in range(n - 1):
        j = int(d.argmax())
        chosen.append(j)
        d = torch.minimum(d, ((pts - pts[j]) ** 2).sum(1))
    return pts[chosen].float()


def _max_filter(m: torch.Tensor, px: int) -> torch.Tensor:
    """Square (2px+1)^2 maximum filter of (B,1,H,W) 0/1 floats (OpenCV's dilation, frame by frame: fast)."""
    import cv2

    kernel = np.ones((2 * px + 1, 2 * px + 1), np.uint8)
    a = (m[:, 0] > 0).numpy().astype(np.uint8)
    out = np.stack([cv2.dilate(f, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0) for f in a])
    return torch.from_numpy(out).float()[:, None]


def _erode(mask: torch.Tensor, px: int) -> torch.Tensor:
    if px <= 0:
        return mask
    grown = _max_filter((~mask).float()[None, None], px)[0, 0] > 0
    return mask & ~grown


def _dilate(mask: torch.Tensor, px: int) -> torch.Tensor:
    """Grow (…,H,W) boolean masks by ``px`` pixels (square structuring element)."""
    if px <= 0:
        return mask
    m = mask.float().reshape(-1, 1, *mask.shape[-2:])
    return (_max_filter(m, px) > 0).reshape(mask.shape)


def _nearest_particles(points: torch.Tensor, particles: torch.Tensor, chunk: int = 4096) -> torch.Tensor:
    best = torch.empty(points.shape[0], dtype=torch.int64)
    for s in range(0, points.shape[0], chunk):
        best[s:s + chunk] = torch.cdist(points[s:s + chunk].double(), particles.double()).argmin(dim=1)
    return best


def visibility(uv: torch.Tensor, z: torch.Tensor, frames: FrameSet, tolerance: float) -> torch.Tensor:
    """(T,N) whether each projected point is in the frame, in front of the camera and not behind the
    rendered surface: its depth is at most the rendered depth plus ``tolerance`` metres, where the
    object covers the pixel (alpha > 0.5). Both are taken leniently over the point's 3x3 pixels (the
    farthest covered depth, any covered pixel), so a surface seen at a grazing angle, whose depth
    changes fast from pixel to pixel, still shows its points; a point behind the object is many
    tolerances behind every pixel around it. Only the 3x3 pixels under each point are read
    (``around_points`` marks them)."""
    return _visible(uv, z, frames.alpha, frames.depth, tolerance)


def _visible(uv: torch.Tensor, z: torch.Tensor, alpha: torch.Tensor, depth: torch.Tensor,
             tolerance: float) -> torch.Tensor:
    T, H, W = alpha.shape
    ix = torch.floor(uv[..., 0]).long()
    iy = torch.floor(uv[..., 1]).long()
    inside = (ix >= 0) & (ix < W) & (iy >= 0) & (iy < H) & (z > 0)
    cx, cy = ix.clamp(0, W - 1), iy.clamp(0, H - 1)
    t = torch.arange(T)[:, None].expand_as(cx)
    near = torch.full(cx.shape, -float("inf"), dtype=depth.dtype)
    on_object = torch.zeros(cx.shape, dtype=torch.bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            x, y = cx + dx, cy + dy
            ok = (x >= 0) & (x < W) & (y >= 0) & (y < H)  # pixels off the image do not count
            x, y = x.clamp(0, W - 1), y.clamp(0, H - 1)
            covered = ok & (alpha[t, y, x] > 0.5)
            on_object |= covered
            near = torch.where(covered, torch.maximum(near, depth[t, y, x]), near)
    front = z <= near + tolerance
    return inside & on_object & front


def around_points(uv: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """(H,W) bool: the pixels ``visibility`` reads for the points uv (N,2): the 3x3 pixels around each."""
    mask = torch.zeros(int(height), int(width), dtype=torch.bool)
    ix = torch.floor(uv[:, 0]).long()
    iy = torch.floor(uv[:, 1]).long()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            x, y = ix + dx, iy + dy
            ok = (x >= 0) & (x < width) & (y >= 0) & (y < height)
            mask[y[ok], x[ok]] = True
    return mask


def _check_track_counts(num_points: int, background_points: int) -> None:
    if not (1 <= int(num_points) <= 4096):
        raise InputError(f"num_points must be between 1 and 4096; got {num_points}")
    if not (0 <= int(background_points) <= 1024):
        raise InputError(f"background_points must be between 0 and 1024; got {background_points}")


def _pick_particles(sim: SimResult, alpha0: torch.Tensor, depth0: torch.Tensor, camera: Camera, num_points: int,
                    edge_px: int) -> torch.Tensor:
    """The particles under ``num_points`` pixels spread evenly over the silhouette of frame 0 (its alpha and
    depth), each once, in sampling order."""
    mask0 = alpha0 > 0.5
    if not bool(mask0.any()):
        raise InputError("The object is not visible in the first frame through this camera (no pixel with alpha > "
                         "0.5), so there is nothing to track. Check the camera and the control size.")
    inner = _erode(mask0, edge_px)  # silhouette edges carry blended depth; sample inside them
    px = sample_even(inner if bool(inner.any()) else mask0, int(num_points))
    ix, iy = px[:, 0].long(), px[:, 1].long()
    surface = camera.unproject(px.double(), depth0[iy, ix].double())
    k = _nearest_particles(surface, sim.x[0])
    _, first = np.unique(k.numpy(), return_index=True)
    return k[torch.from_numpy(np.sort(first))]  # two pixels on one particle: keep it once, in sampling order


def _depth_tolerance(sim: SimResult, depth_tolerance: float) -> float:
    """``depth_tolerance`` when given, else 1.5 particle spacings: the particle under a surface point lies up to
    about one spacing inside the surface."""
    if depth_tolerance > 0:
        return float(depth_tolerance)
    spacing = float(sim.stats.get("particle_spacing", 0.0)) or 0.01 * float(
        (sim.rest_particles.max(0).values - sim.rest_particles.min(0).values).max())
    return 1.5 * spacing


def _with_background(tracks_uv, vis, k, never: torch.Tensor, background_points: int, alpha=None):
    """Adds ``background_points`` still anchors sampled evenly over ``never`` (pixels the object never covers,
    shrunk by 4 px); visible wherever ``alpha`` (T,H,W), when given, is below 0.5, else always."""
    T = tracks_uv.shape[0]
    bg = sample_even(_erode(never, 4), int(background_points))
    if not bg.shape[0]:
        return tracks_uv, vis, k
    bix, biy = bg[:, 0].long(), bg[:, 1].long()
    bvis = alpha[:, biy, bix] < 0.5 if alpha is not None else torch.ones(T, bg.shape[0], dtype=torch.bool)
    return (torch.cat([tracks_uv, bg[None].expand(T, -1, -1).double()], dim=1), torch.cat([vis, bvis], dim=1),
            torch.cat([k, torch.full((bg.shape[0],), -1, dtype=torch.int64)]))


def point_tracks(sim: SimResult, frames: FrameSet, camera: Camera, num_points: int = 64, *,
                 background_points: int = 0, depth_tolerance: float = 0.0, edge_px: int = 2) -> Tracks:
    """Tracks of ``num_points`` object points spread evenly over the object's silhouette in frame 0,
    plus ``background_points`` still anchors on background pixels the object never covers, from a rendered
    clip (``probe_tracks`` does the same from the simulation alone, rendering only frame 0 and the pixels
    the points need).

    ``sim`` and ``frames`` must hold the same frames (render the resampled simulation). Each object
    point is the physics particle nearest the surface point seen at a sampled pixel (the pixel
    unprojected at its rendered depth); its track is that particle's position projected through
    ``camera`` every frame, visible where it is not behind the rendered surface (``visibility``;
    ``depth_tolerance`` 0 = 1.5 particle spacings: the particle under a surface point lies up to about one
    spacing inside the surface)."""
    T, H, W = frames.alpha.shape
    if T != sim.num_frames:
        raise InputError(f"The frames ({T}) and the simulation ({sim.num_frames} frames) differ: render the same "
                         "(resampled) simulation the tracks follow.")
    if (W, H) != (camera.width, camera.height):
        raise InputError(f"The frames are {W}x{H} but the camera is {camera.width}x{camera.height}")
    _check_track_counts(num_points, background_points)
    k = _pick_particles(sim, frames.alpha[0], frames.depth[0], camera, num_points, edge_px)
    uv, z = camera.project(sim.x[:, k].reshape(-1, 3).double())
    uv, z = uv.reshape(T, -1, 2), z.reshape(T, -1)
    vis = visibility(uv, z, frames, _depth_tolerance(sim, depth_tolerance))
    particle = k
    if background_points:
        never = ~_dilate(frames.alpha.amax(0) > 0.05, 4)
        uv, vis, particle = _with_background(uv, vis, k, never, background_points, frames.alpha)
    return Tracks(uv=uv.float(), visible=vis, particle=particle, width=W, height=H, fps=float(frames.fps))


def probe_tracks(sim: SimResult, camera: Camera, num_points: int = 64, *, background_points: int = 0,
                 depth_tolerance: float = 0.0, edge_px: int = 2, backend: str = "auto",
                 device: Optional[str] = None,
                 progress: Optional[ProgressFn] = None) -> tuple[Tracks, FrameSet]:
    """``point_tracks`` without rendering the clip: the same tracks (the same points, positions and
    visibility), and frame 0's render (for a preview).

    Frame 0 is rendered whole (its silhouette and depth pick the points). In every later frame only the
    3x3 pixels around each point are rendered (``render.rasterize.probe``: the rasterizer's own projection,
    order and compositing over the tiles that hold them, so the depth and alpha there are the whole frame's
    to round-off). The background anchors go where no splat's box ever reaches (a conservative "never
    covered", so they need no visibility test). ``device``: where the renders and probes run (default the CPU)."""
    from .render.frames import frame_threads, repeated_frames, run_frame_blocks
    from .render.rasterize import probe, rasterize

    _check_track_counts(num_points, background_points)
    T, H, W = sim.num_frames, int(camera.height), int(camera.width)
    dev = torch.device(device) if device is not None else torch.device("cpu")
    with torch.no_grad():
        out = rasterize(sim.gaussians_at(0).to(dev), camera, backend=backend)
    first = FrameSet(rgb=out.rgb.cpu()[None], alpha=out.alpha.cpu()[None], depth=out.depth.cpu()[None],
                     fps=sim_fps(sim))
    k = _pick_particles(sim, first.alpha[0], first.depth[0], camera, num_points, edge_px)
    uv, z = camera.project(sim.x[:, k].reshape(-1, 3).double())
    uv, z = uv.reshape(T, -1, 2), z.reshape(T, -1)
    tol = _depth_tolerance(sim, depth_tolerance)
    vis = torch.zeros(T, k.numel(), dtype=torch.bool)
    vis[0] = _visible(uv[:1], z[:1], first.alpha, first.depth, tol)[0]
    covered = [first.alpha[0] > 0]

    repeated = repeated_frames(sim)

    def work(a: int, b: int, done) -> None:  # frames 1 + a .. b (blocks on several threads on the CPU)
        seen = torch.zeros(H, W, dtype=torch.bool)
        for t in range(1 + a, 1 + b):
            if t > 1 + a and repeated[t]:  # at rest: the same points, probed to the same values
                vis[t] = vis[t - 1]
                done(t - 1)
                continue
            p = probe(sim.gaussians_at(t).to(dev), camera, around_points(uv[t], W, H))
            vis[t] = _visible(uv[t:t + 1], z[t:t + 1], p.alpha.cpu()[None], p.depth.cpu()[None], tol)[0]
            seen |= p.footprint.cpu()
            done(t - 1)
        covered.append(seen)

    report(progress, 1, T)
    run_frame_blocks(T - 1, frame_threads(T - 1, dev), work,
                     None if progress is None else lambda k, n: report(progress, k + 1, n + 1),
                     cost=[0 if r and t > 1 else 1 for t, r in enumerate(repeated) if t >= 1])
    covered = torch.stack(covered).any(0)
    particle = k
    if background_points:
        uv, vis, particle = _with_background(uv, vis, k, ~_dilate(covered, 4), background_points)
    tracks = Tracks(uv=uv.float(), visible=vis, particle=particle, width=W, height=H, fps=sim_fps(sim))
    return tracks, first


def scaled_tracks(tracks: Tracks, width: int, height: int) -> Tracks:
    """The tracks of a ``tracks.width`` x ``tracks.height`` frame in a ``width`` x ``height`` frame of the same
    view (intrinsics scaled: ``Camera.resized``), where pixel coordinates scale exactly: u' = u width / w."""
    sx, sy = width / tracks.width, height / tracks.height
    uv = tracks.uv * torch.tensor([sx, sy], dtype=tracks.uv.dtype)
    return dataclasses.replace(tracks, uv=uv, width=int(width), height=int(height))


def wan_sample_frames(length: int) -> tuple[np.ndarray, np.ndarray]:
    """For a WanTrackToVideo clip of ``length`` frames: the output frame (fractional where the node
    skips the sample) each of the 121 track samples stands for, and which samples the node reads
    (see the module docstring for the index rule of ``process_tracks`` at 0.3.64; unchanged upstream at
    the newest commit read, see docs/comfyui.md). Above 121 frames several consecutive frames read one
    sample, which then stands for the middle of them (``wan_shared_samples`` says how many)."""
    F = check_length(length) - 1
    if F % 120 == 0:
        # repeat_interleave(b)[1::a] with a = 1 yields F - 1 frames: the node's own reshape then fails.
        raise InputError(f"WanTrackToVideo (ComfyUI 0.3.64) cannot take length={length}: when length-1 is a multiple "
                         f"of 120 its track resampling returns one frame too few. Use {length - 4} or {length + 4}.")
    g = math.gcd(120, F)
    a, b = 120 // g, F // g
    read = np.zeros(WAN_TRACK_SAMPLES, bool)
    first = np.full(WAN_TRACK_SAMPLES, np.inf)
    last = np.full(WAN_TRACK_SAMPLES, -np.inf)
    read[0], first[0], last[0] = True, 0.0, 0.0
    for j in range(1, F + 1):
        s = 1 + (1 + a * (j - 1)) // b
        read[s] = True
        first[s], last[s] = min(first[s], j), max(last[s], j)
    # Up to 121 frames every frame reads its own sample. A longer clip has fewer samples than frames, so
    # consecutive frames share one: the sample is placed at the middle of the frames that read it, so none
    # of them sees a position more than half the span away in time (placed at the first, the last would
    # see it up to the whole span late).
    frame_of = np.full(WAN_TRACK_SAMPLES, np.nan)
    frame_of[read] = 0.5 * (first[read] + last[read])
    known = np.nonzero(read)[0]
    frame_of = np.interp(np.arange(WAN_TRACK_SAMPLES), known, frame_of[known])
    # Samples after the last one read stand for nothing the model sees; keep them on the last frame.
    return np.clip(frame_of, 0, F), read


def wan_shared_samples(length: int) -> tuple[int, float]:
    """For a WanTrackToVideo clip of ``length`` frames: how many frames read a sample that another frame
    reads too, and the largest time (in frames) between a frame and the moment its sample shows. Both are 0
    up to 121 frames; above, the 121 samples cannot give every frame its own position."""
    F = check_length(length) - 1
    frame_of, read = wan_sample_frames(length)
    g = math.gcd(120, F)
    a, b = 120 // g, F // g
    samples = np.array([0] + [1 + (1 + a * (j - 1)) // b for j in range(1, F + 1)])
    shared = int(np.sum(np.bincount(samples)[samples] > 1))
    lag = float(np.max(np.abs(frame_of[samples] - np.arange(F + 1)))) if F else 0.0
    return shared, lag


def wan_tracks_json(tracks: Tracks, length: Optional[int] = None, occlusion: str = "end", decimals: int = 2) -> str:
    """The ``tracks`` STRING for WanTrackToVideo (``length`` = its length input; default the tracks'
    frame count, which must then be 4k+1). Tracks must be at the model's frames (16 fps for Wan).

    ``occlusion``: "end" ends a track at its first hidden sample (the parser pads the rest as
    invisible; the format has no visibility field), "keep" lists every sample."""
    if occlusion not in ("end", "keep"):
        raise InputError(f"occlusion must be 'end' or 'keep'; got {occlusion!r}")
    length = tracks.num_frames if length is None else int(length)
    if length != tracks.num_frames:
        raise InputError(f"The tracks have {tracks.num_frames} frames but WanTrackToVideo's length is {length}: "
                         "make the tracks at the same length.")
    frame_of, _ = wan_sample_frames(length)
    if length > WAN_TRACK_SAMPLES:
        shared, lag = wan_shared_samples(length)
        log.warning("WanTrackToVideo reads 121 track samples; a %d-frame clip has more frames than samples, so %d "
                    "frames share a sample with a neighbour (each sample is placed at the middle of the frames that "
                    "read it: a frame's position is at most %.1f frame(s) from its own time). For one position per "
                    "frame, keep the clip at 121 frames or fewer.", length, shared, lag)
    f0 = np.floor(frame_of).astype(np.int64).clip(0, length - 1)
    f1 = np.minimum(f0 + 1, length - 1)
    w = torch.from_numpy(frame_of - f0).float()[:, None, None]
    uv = tracks.uv[f0] * (1 - w) + tracks.uv[f1] * w  # (121, N, 2)
    frac = torch.from_numpy(frame_of - f0)[:, None]
    vis = tracks.visible[f0] & (tracks.visible[f1] | (frac < 1e-9))
    # Rounded once as an array (np.round: the double nearest k / 10^decimals, so each prints as its short
    # decimal), written as json.dumps writes [[{"x":..,"y":..},..],..] with separators (",", ":").
    # A point crossing the camera's plane projects to ±inf or NaN: written far off the frame (it is hidden there,
    # so "end" ends its track before), since JSON has no such numbers.
    a = np.nan_to_num(uv.numpy().astype(np.float64), nan=-1e6, posinf=1e6, neginf=-1e6).clip(-1e6, 1e6)
    xy = np.round(a, decimals).transpose(1, 0, 2).tolist()  # (N, 121, 2)
    visn = vis.numpy()
    tracks_out = []
    for n in range(tracks.num_points):
        count = WAN_TRACK_SAMPLES
        if occlusion == "end":
            hidden = np.flatnonzero(~visn[:, n])
            count = int(hidden[0]) if hidden.size else WAN_TRACK_SAMPLES
        if count == 0:
            continue
        tracks_out.append("[" + ",".join(f'{{"x":{x!r},"y":{y!r}}}' for x, y in xy[n][:count]) + "]")
    return "[" + ",".join(tracks_out) + "]"


def _track_colours(n: int) -> np.ndarray:
    import cv2

    hsv = np.stack([(np.arange(n) * 137.508) % 180, np.full(n, 220), np.full(n, 255)], 1).astype(np.uint8)
    return cv2.cvtColor(hsv[None], cv2.COLOR_HSV2RGB)[0]


def draw_tracks(images: torch.Tensor, tracks: Tracks, trail: int = 8, radius: int = 0) -> torch.Tensor:
    """The frames (T,H,W,3) with each track drawn: a filled dot where the point is visible, a ring
    where it is hidden, and a trail of its last ``trail`` frames."""
    import cv2

    if images.ndim != 4 or images.shape[0] != tracks.num_frames or images.shape[1:3] != (tracks.height, tracks.width):
        raise InputError(f"draw_tracks: images {tuple(images.shape)} do not match the tracks' "
                         f"{tracks.num_frames} frames of {tracks.width}x{tracks.height}")
    r = radius or max(2, round(min(tracks.width, tracks.height) / 120))
    cols = _track_colours(tracks.num_points)
    uv = tracks.uv.numpy()
    vis = tracks.visible.numpy()
    out = np.empty((tracks.num_frames, tracks.height, tracks.width, 3), dtype=np.uint8)
    base, base_ptr = None, None
    for t in range(tracks.num_frames):
        if images[t].data_ptr() != base_ptr or base is None:  # one frame expanded over the clip: converted once
            base_ptr = images[t].data_ptr()
            base = (images[t, ..., :3].clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
        img = out[t]
        img[...] = base
        for n in range(tracks.num_points):
            c = tuple(int(v) for v in cols[n])
            pts = [(float(uv[s, n, 0]), float(uv[s, n, 1])) for s in range(max(0, t - trail), t + 1) if vis[s, n]]
            for p, q in zip(pts[:-1], pts[1:]):
                cv2.line(img, (round(p[0] - 0.5), round(p[1] - 0.5)), (round(q[0] - 0.5), round(q[1] - 0.5)), c, 1,
                         cv2.LINE_AA)
            centre = (round(float(uv[t, n, 0]) - 0.5), round(float(uv[t, n, 1]) - 0.5))
            cv2.circle(img, centre, r, c, -1 if vis[t, n] else 1, cv2.LINE_AA)
    return torch.from_numpy(out).float().div_(255.0)


# ----------------------------------------------------------------------------------------------
# Control videos
# ----------------------------------------------------------------------------------------------


@dataclass
class ControlVideos:
    """All (T,H,W,3) IMAGE batches except ``mask`` (T,H,W)."""

    depth: torch.Tensor
    render: torch.Tensor
    mask: torch.Tensor
    blended: torch.Tensor
    vace: torch.Tensor


def over_background(rgb: torch.Tensor, alpha: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """``blend.composite`` (premultiplied ``rgb`` (T,H,W,3) with ``alpha`` over ``background`` (H,W,3) or
    (T,H,W,3), clamped to 0..1), the same values, with one clip-sized allocation instead of three: a Wan
    clip is hundreds of MB and on a VM every fresh page costs."""
    from .blend import composite

    bg = background[..., :3]
    if rgb.ndim != 4 or alpha.shape != rgb.shape[:3] or bg.shape[-3:-1] != rgb.shape[1:3]:
        return composite(rgb, alpha, bg)  # its checks and messages
    out = (1.0 - alpha)[..., None] * bg.to(rgb.device, rgb.dtype)
    return out.add_(rgb).clamp_(0.0, 1.0)  # rgb + (1 - alpha) bg: addition commutes exactly


def control_videos(frames: FrameSet, background: Optional[torch.Tensor] = None, grow_mask: int = 0) -> ControlVideos:
    """The control videos of a rendered clip (already at the model's size and clock).

    depth: inverse depth, near = bright, normalised over the whole clip (no flicker), black where
    there is no object (the convention of the depth maps Wan's control models are trained on:
    Depth-Anything/MiDaS-style disparity); render: the object over black; mask: the object
    (alpha > 0.5) grown by ``grow_mask`` px; blended: the object over ``background`` (the coarse
    video; the render when there is no background); vace: depth inside the mask, the blended video
    outside, for WanVaceToVideo with ``control_masks`` = mask (regenerate the object following the
    physics, keep the rest)."""
    from .render.frames import depth_to_image

    depth = depth_to_image(frames.depth, frames.alpha)
    inside = _dilate(frames.alpha > 0.5, int(grow_mask))
    render = frames.rgb.clamp(0, 1)
    blended = over_background(frames.rgb, frames.alpha, background) if background is not None else render
    vace = torch.where(inside[..., None], depth, blended)  # depth * mask + blended * (1 - mask), in one pass
    return ControlVideos(depth=depth, render=render, mask=inside.float(), blended=blended, vace=vace)


# ----------------------------------------------------------------------------------------------
# Exact optical flow
# ----------------------------------------------------------------------------------------------


@dataclass
class Flow:
    """Optical flow per frame pair: ``flow`` (T-1,H,W,2) in pixels (dx, dy), ``valid`` (T-1,H,W) where
    the object covers the pixel in the source frame (elsewhere the flow is 0: the background is still).

    forward: pixel p of frame t shows the point that frame t+1 shows at p + flow[t, p] (so sampling
    frame t+1 at p + flow reproduces frame t: OpenCV's calcOpticalFlowFarneback(prev=t, next=t+1)
    convention); backward: the same from frame t+1 to frame t."""

    flow: torch.Tensor
    valid: torch.Tensor
    fps: float
    direction: str = "forward"


def _splat_linear_part(sim: SimResult, frame: int) -> torch.Tensor:
    """(P,3,3) float64: the deformation gradient each particle's splats follow at ``frame``, clamped as
    ``gaussians_at`` clamps it (stretch only for flowing material: ``splat_deformation``, which runs
    the SVD only where the clamp can change F)."""
    from .types.results import MAX_SPLAT_STRETCH, splat_deformation

    return splat_deformation(sim.F[frame].double(), MAX_SPLAT_STRETCH, sim.rotation_free)


def _inverse(L: torch.Tensor) -> torch.Tensor:
    """Inverses of (N,3,3) matrices; the pseudo-inverse for the (rare) singular ones."""
    inv, info = torch.linalg.inv_ex(L)
    bad = (info != 0) | ~torch.isfinite(inv).all(dim=(1, 2))
    if bool(bad.any()):
        inv[bad] = torch.linalg.pinv(L[bad])
    return inv


def _pixel_grid(camera: Camera) -> torch.Tensor:
    ys, xs = torch.meshgrid(torch.arange(camera.height, dtype=torch.float64) + 0.5,
                            torch.arange(camera.width, dtype=torch.float64) + 0.5, indexing="ij")
    return torch.stack([xs, ys], dim=-1)  # (H,W,2)


#: Per-Gaussian flow channels rendered with the colour (see ``render_clip``).
FLOW_CHANNELS = 9
#: Frames whose splats all move by one affine map (rigid bodies) take their flow from the rendered depth instead
#: of 9 composited channels (``_one_map``); False renders the channels always (the tests compare the two).
ONE_MAP_FLOW = True


#: Largest flow error (px) accepted from reading a frame's motion as one rigid map (``_one_map``).
ONE_MAP_TOLERANCE_PX = 1e-3


def _flow_maps(sim: SimResult, w2c: torch.Tensor, mu_s: torch.Tensor, L_s: torch.Tensor, mu_d: torch.Tensor,
               L_d: torch.Tensor):
    """Each Gaussian's affine map x -> A x + b from frame s to frame d, in camera coordinates (float64): A (N,3,3)
    = R L_d L_s^-1 Rᵀ of the deformation its particle's splats follow, b (N,3) = its mean's destination - A times
    its mean; and its mean at frame s (N,3)."""
    R, t = w2c[:3, :3], w2c[:3, 3]
    A = (R @ (L_d @ _inverse(L_s)) @ R.T)[sim.binding]  # per particle, in camera coordinates; per Gaussian
    ms = mu_s @ R.T + t
    md = mu_d @ R.T + t
    b = md - (A @ ms[..., None])[..., 0]
    return A, b, ms


def _one_map(A: torch.Tensor, b: torch.Tensor, ms: torch.Tensor, camera: Camera):
    """(A, b) when every Gaussian moves by the same affine map (a rigid body, or a still frame), else None: the
    largest difference from the mean map, applied to the farthest mean, moves a point by at most
    ``ONE_MAP_TOLERANCE_PX`` px at the nearest depth. Then the composited flow channels are that map applied to
    the rendered surface point (depth times the pixel's ray), so the frame needs none."""
    if A.shape[0] == 0:
        return None
    A0, b0 = A.mean(0), b.mean(0)
    dA = float((A - A0).flatten(1).norm(dim=1).max())
    db = float((b - b0).norm(dim=1).max())
    z = ms[:, 2]
    near = float(z[z > 0].min()) if bool((z > 0).any()) else 0.0
    if near <= 0.0:
        return None
    err_px = max(camera.fx, camera.fy) / near * (dA * float(ms.norm(dim=1).max()) + db)
    return (A0, b0) if err_px <= ONE_MAP_TOLERANCE_PX else None


def _flow_features(sim: SimResult, w2c: torch.Tensor, mu_s: torch.Tensor, L_s: torch.Tensor, mu_d: torch.Tensor,
                   L_d: torch.Tensor, maps=None) -> torch.Tensor:
    """(N,9) per-Gaussian channels G (3x3, row-major) such that, composited like colour, G(p) r(p) / alpha
    is where the surface point seen at pixel p goes (camera coordinates), r(p) = ((u-cx)/fx, (v-cy)/fy, 1).

    Each Gaussian moves from frame s to frame d by an affine map x -> A x + b (A = L_d L_s^-1 of the
    deformation its splat follows, b = mu_d - A mu_s), here in camera coordinates. The point at depth z on
    pixel p's ray is X = z r(p), so A X + b = (z A) r(p) + b: the columns of G are z A[:, 0], z A[:, 1] and
    z A[:, 2] + b with z the Gaussian's own depth. Composited, the pixel gets A (sum w z) r + b alpha for
    splats that share a motion, and sum w z / alpha is exactly the rendered (expected) depth: exact for rigid
    motion, first order in the splat size for deforming material. ``maps``: ``_flow_maps``' result, if made."""
    A, b, ms = _flow_maps(sim, w2c, mu_s, L_s, mu_d, L_d) if maps is None else maps
    G = A * ms[:, 2, None, None]
    G[:, :, 2] += b
    return G.reshape(-1, FLOW_CHANNELS)


def _repeats_previous(repeated: list, t: int, d: int, flow: Optional[str]) -> bool:
    """Whether ``render_clip``'s frame t (with the flow channels toward frame d when there is a flow) is its frame
    t-1's, bit for bit: the same pose (``repeated``: ``render.frames.repeated_frames``) and, with a flow, the same
    pose at both frames' destinations (forward: t+1 and t; backward: t-1 and t-2), so that both carry the
    channels or neither."""
    if not repeated[t]:
        return False
    if flow is None:
        return True
    T = len(repeated)
    has, had = 0 <= d < T, 0 <= d - 1 < T  # frame t-1's destination is d - 1
    if has != had:
        return False
    return not has or repeated[d]


def render_clip(sim: SimResult, camera: Camera, *, flow: Optional[str] = None, device: Optional[str] = None,
                backend: str = "auto", progress: Optional[ProgressFn] = None) -> tuple[FrameSet, Optional["Flow"]]:
    """Every frame rendered once (RGB, alpha, depth as ``render_frames``) and, with ``flow`` ("forward" or
    "backward"), the exact optical flow of the clip from the same renders: each frame carries 9 more
    composited channels (``_flow_features``) that map its visible surface points to the next (forward) or
    previous (backward) frame; a frame whose splats all move by one affine map (a rigid body: ``_one_map``)
    needs none, its flow is that map applied to the rendered depth. So the control videos and the flow of one
    clip cost one render, posing each frame once (twice at the edges of the blocks of frames that render at once
    on the CPU: ``frame_threads``)."""
    from .render.frames import check_frames_fit, frame_threads, repeated_frames, run_frame_blocks
    from .render.rasterize import rasterize

    if flow not in (None, "forward", "backward"):
        raise InputError(f"direction must be 'forward' or 'backward'; got {flow!r}")
    T = sim.num_frames
    if flow is not None and T < 2:
        raise InputError("Optical flow needs at least two frames; the simulation has one.")
    dev = torch.device(device) if device is not None else torch.device("cpu")
    H, W = int(camera.height), int(camera.width)
    # RGB + alpha + depth, and flow (2 floats) + valid (1 byte) per pair.
    check_frames_fit(T, W, H, "The render", per_pixel=20 + (9 if flow else 0))
    rgb, alpha, depth = torch.empty(T, H, W, 3), torch.empty(T, H, W), torch.empty(T, H, W)
    if flow is not None:
        flows = torch.zeros(T - 1, H, W, 2)
        valid = torch.zeros(T - 1, H, W, dtype=torch.bool)
        w2c = camera.w2c_opencv().double()
        grid = _pixel_grid(camera)
        ray = torch.stack([(grid[..., 0] - camera.cx) / camera.fx, (grid[..., 1] - camera.cy) / camera.fy,
                           torch.ones(H, W, dtype=torch.float64)], -1)  # (H,W,3): r(p)

    repeated = repeated_frames(sim)

    def work(a: int, b: int, done) -> None:
        """Frames a..b-1, in order (a block of its own when several frames render at once)."""
        posed: dict = {}

        def pose(f):  # each frame posed once in a block: it is a source and a destination of flow
            if f not in posed:
                for old in [k for k in posed if abs(k - f) > 1]:
                    del posed[old]
                g = sim.gaussians_at(f)
                posed[f] = (g, g.means.double(), _splat_linear_part(sim, f) if flow is not None else None)
            return posed[f]

        with torch.no_grad():
            for t in range(a, b):
                d = t + 1 if flow == "forward" else t - 1 if flow == "backward" else -1
                if t > a and _repeats_previous(repeated, t, d, flow):
                    rgb[t], alpha[t], depth[t] = rgb[t - 1], alpha[t - 1], depth[t - 1]
                    if 0 <= d < T:  # and the previous frame's flow pair
                        pair, before = (t, t - 1) if flow == "forward" else (d, d - 1)
                        flows[pair], valid[pair] = flows[before], valid[before]
                    done(t)
                    continue
                g, mu, L = pose(t)
                feats = one = None
                if 0 <= d < T:
                    _, mu_d, L_d = pose(d)
                    maps = _flow_maps(sim, w2c, mu, L, mu_d, L_d)
                    one = _one_map(*maps, camera) if ONE_MAP_FLOW else None
                    if one is None:  # each splat its own map: composited as 9 more channels
                        feats = _flow_features(sim, w2c, mu, L, mu_d, L_d, maps).to(g.means.dtype).to(dev)
                out = rasterize(g.to(dev), camera, extra_features=feats, backend=backend)
                a_t = out.alpha.cpu()
                rgb[t], alpha[t], depth[t] = out.rgb.cpu(), a_t, out.depth.cpu()
                if feats is not None or one is not None:
                    pair = t if flow == "forward" else d
                    ok = a_t > 0.5
                    rows, cols = ok.any(1).nonzero(), ok.any(0).nonzero()
                    if rows.numel():
                        # Over the box the object covers (cheaper than gathering the pixels by mask, the same values
                        # at them): the pixels it does not cover get 0.
                        y0, y1, x0, x1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
                        o = ok[y0:y1, x0:x1]
                        r = ray[y0:y1, x0:x1]
                        if one is not None:  # one map: applied to the rendered surface point, depth times the ray
                            A0, b0 = one
                            D = depth[t, y0:y1, x0:x1].double()[..., None] * (r @ A0.T) + b0
                        else:
                            a_box = torch.where(o, a_t[y0:y1, x0:x1], 1.0).double()
                            e = (out.extra[y0:y1, x0:x1].cpu().double() / a_box[..., None]).view(y1 - y0, x1 - x0,
                                                                                                 3, 3)
                            D = e[..., 0] * r[..., 0:1] + e[..., 1] * r[..., 1:2] + e[..., 2]  # where the point goes
                        uv = torch.stack([camera.fx * D[..., 0] / D[..., 2] + camera.cx,
                                          camera.fy * D[..., 1] / D[..., 2] + camera.cy], -1)
                        flows[pair, y0:y1, x0:x1] = torch.where(o[..., None], uv - grid[y0:y1, x0:x1], 0.0).float()
                        valid[pair] = ok
                done(t)

    run_frame_blocks(T, frame_threads(T, dev), work, progress, cost=[0 if r else 1 for r in repeated])
    frames = FrameSet(rgb=rgb, alpha=alpha, depth=depth, fps=sim_fps(sim))
    if flow is None:
        return frames, None
    return frames, Flow(flow=flows, valid=valid, fps=sim_fps(sim), direction=flow)


def exact_flow(sim: SimResult, camera: Camera, *, direction: str = "forward", device: Optional[str] = None,
               backend: str = "auto", progress: Optional[ProgressFn] = None) -> Flow:
    """The optical flow of the rendered clip, from the simulation itself (``render_clip``, which renders
    the frames too: use it directly when the frames are wanted as well).

    Every Gaussian moves from frame s to frame d by an affine map x -> A x + b (A = L_d L_s^-1, b =
    mu_d - A mu_s: mu its centre, L the deformation gradient its splat follows). Rendered at frame s like
    colour (the same compositing weights as the image), each visible pixel gets the blended map of the
    splats behind it, applied to its surface point (on the pixel's ray at the rendered depth), which is
    projected: flow = project(A x + b) - p. Exact for rigid motion; for deforming material it is first
    order in the splat size."""
    return render_clip(sim, camera, flow=direction, device=device, backend=backend, progress=progress)[1]


def flow_to_color(flow: torch.Tensor, max_flow: float = 0.0) -> torch.Tensor:
    """Colour-wheel picture (…,H,W,3) of flow (…,H,W,2): hue = direction (red = +x, right), saturation =
    speed / ``max_flow`` (0 = the largest flow in the batch), white = still."""
    import cv2

    f = flow.detach().float().cpu().numpy()
    shape = f.shape[:-1]
    fx = np.ascontiguousarray(f[..., 0]).reshape(-1, shape[-1] if len(shape) else 1)
    fy = np.ascontiguousarray(f[..., 1]).reshape(fx.shape)
    mag, ang = cv2.cartToPolar(fx, fy, angleInDegrees=True)  # float32, angle in [0, 360)
    top = float(max_flow) if max_flow > 0 else float(mag.max()) if mag.size else 0.0
    hsv = np.empty(mag.shape + (3,), np.uint8)
    hsv[..., 0] = (ang * 0.5).astype(np.uint8)  # OpenCV's hue runs 0..180
    hsv[..., 1] = (np.minimum(mag * (1.0 / max(top, 1e-9)), 1.0) * 255.0).astype(np.uint8)
    hsv[..., 2] = 255
    rgb = cv2.cvtColor(hsv.reshape(-1, 1, 3), cv2.COLOR_HSV2RGB).reshape(shape + (3,))
    return torch.from_numpy(rgb).float().div_(255.0)


def save_flow_npz(path, flow: Flow, camera: Optional[Camera] = None) -> str:
    """Write the flow atomically as a compressed .npz: flow (T-1,H,W,2) float32 px, valid (T-1,H,W) bool,
    fps, direction, the convention in words, and the camera (intrinsics, c2w) when given."""
    from .fsutil import atomic_output

    arrays = {"flow": flow.flow.numpy().astype(np.float32), "valid": flow.valid.numpy(),
              "fps": np.float64(flow.fps), "direction": np.str_(flow.direction),
              "convention": np.str_("flow[t,y,x] = (dx, dy) px; pixel centres at +0.5; forward: frame t+1 at p+flow "
                                    "shows what frame t shows at p (backward: from t+1 to t)")}
    if camera is not None:
        arrays["K"] = camera.K().numpy()
        arrays["c2w"] = camera.c2w.numpy()
    import zipfile

    # np.savez_compressed at zlib's fastest level: the flow is mostly exact zeros (the still background),
    # which level 1 packs about as well as the default level in a fraction of the time. A standard .npz.
    with atomic_output(path, suffix=".tmp.npz") as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
            for name, value in arrays.items():
                with zf.open(name + ".npy", "w", force_zip64=True) as fh:
                    np.lib.format.write_array(fh, np.asanyarray(value), allow_pickle=False)
    return str(path)
