"""Render every frame of a simulation through a camera."""

from __future__ import annotations

import os
import queue
import threading
from typing import Callable, Optional

import torch

from ..errors import InputError
from ..memory import host_available_bytes
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
        from ..memory import over_limit_message

        raise InputError(f"{what} ({frames} frames of {width}x{height}) {over_limit_message(need, have, fraction)}. "
                         f"Lower the frame count (at most about {fit} at this size) or the image size (e.g. scale the "
                         "photo down before lifting).")


def frame_threads(frames: int, device: torch.device) -> int:
    """How many frames the CPU renders at once: one per torch thread (PHYSMOTION_RENDER_THREADS overrides; 1 =
    one frame at a time, as before), at most one per frame; 1 off the CPU, where a frame fills the device.

    Each frame's compositing is a loop of small tensor operations whose fixed cost does not shrink with more
    intra-op threads, so whole frames on separate threads, each with one torch thread, use the cores better
    than one frame on all of them."""
    if torch.device(device).type != "cpu" or frames < 2:
        return 1
    env = os.environ.get("PHYSMOTION_RENDER_THREADS", "").strip()
    n = int(env) if env.isdigit() and int(env) > 0 else torch.get_num_threads()
    return max(1, min(n, frames))


def _block_bounds(total: int, threads: int, cost: Optional[list] = None) -> list:
    """Bounds of ``threads`` contiguous blocks of ``total`` frames: equal counts, or, given each frame's ``cost``,
    about equal sums of it (frames that copy the one before cost next to nothing)."""
    if cost is None or len(cost) != total or sum(cost) <= 0:
        return [round(i * total / threads) for i in range(threads + 1)]
    run, acc = [], 0.0
    for c in cost:
        acc += float(c)
        run.append(acc)  # cost of frames 0..k
    bounds = [0]
    for i in range(1, threads):
        goal = i * acc / threads
        k = next((j + 1 for j, r in enumerate(run) if r >= goal), total)  # the block ends once it holds its share
        bounds.append(min(max(k, bounds[-1]), total))
    return bounds + [total]


def run_frame_blocks(total: int, threads: int, work: Callable[[int, int, Callable[[int], None]], None],
                     progress: Optional[ProgressFn] = None, cost: Optional[list] = None) -> None:
    """Runs ``work(start, stop, done)`` over ``threads`` contiguous blocks of frames, each block on its own thread
    with one torch thread (restored afterwards); ``work`` calls ``done(k)`` after frame k. Progress is reported
    from the calling thread, one step per finished frame; when it raises (ComfyUI's Cancel) the workers stop at
    their next frame and the exception goes on. A worker's exception is raised here. With one thread, ``work``
    runs here, as a plain loop. ``cost`` (one number per frame) balances the blocks by it instead of by count."""
    if threads <= 1:
        work(0, total, lambda k: None if progress is None else report(progress, k + 1, total))
        return
    bounds = _block_bounds(total, threads, cost)
    finished: queue.Queue = queue.Queue()
    stop = threading.Event()

    class _Stopped(Exception):
        pass

    def done(k: int) -> None:
        finished.put(k)
        if stop.is_set():
            raise _Stopped

    inference = torch.is_inference_mode_enabled()  # ComfyUI runs nodes in it; it is per thread, like no_grad

    def run(a: int, b: int) -> None:
        try:
            if not stop.is_set():
                with torch.inference_mode(inference), torch.no_grad():
                    work(a, b, done)
        except _Stopped:
            pass
        except BaseException as exc:  # handed to the calling thread
            finished.put(exc)
        finally:
            finished.put(None)

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    workers = [threading.Thread(target=run, args=(bounds[i], bounds[i + 1]), daemon=True,
                                name=f"physmotion-render-{i}") for i in range(threads) if bounds[i + 1] > bounds[i]]
    try:
        for w in workers:
            w.start()
        running, count = len(workers), 0
        while running:
            item = finished.get()
            if item is None:
                running -= 1
            elif isinstance(item, BaseException):
                stop.set()
                raise item
            else:
                count += 1
                report(progress, count, total)
    except BaseException:
        stop.set()
        raise
    finally:
        for w in workers:
            w.join()
        torch.set_num_threads(before)


def repeated_frames(sim: SimResult) -> list:
    """Per frame: whether it is posed bit for bit as the frame before (``SimResult.same_pose``), so a renderer
    copies the frame before instead of drawing it. Frame 0 never is."""
    return [k > 0 and sim.same_pose(k, k - 1) for k in range(sim.num_frames)]


def render_frames(sim: SimResult, camera: Camera, *, device: Optional[torch.device | str] = None,
                  progress: Optional[ProgressFn] = None, backend: str = "auto", photo=None) -> FrameSet:
    """RGB (premultiplied), alpha and expected depth for every simulated frame (on the CPU, several frames at
    once: ``frame_threads``). A frame posed exactly as the one before it (``SimResult.same_pose``: the object at
    rest) gets that frame's render, copied, not drawn again.

    ``photo``: a ``photo_texture.PhotoTexture`` of the input photo: the surface the photo saw shows the photo's
    own pixels, carried back to rest by each splat's motion (``photo_texture``), and the splats it did not see show
    their colours low-passed in 3D (``photo_texture.UNSEEN_BLUR_CELLS``); None renders the splats' colours only.

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

    repeated = repeated_frames(sim)
    poser = None
    threads = frame_threads(total, dev)
    if photo is not None:
        from .photo_texture import TexturedPoser

        # The texture's set-up (the seen test's rest render, the rest pose's maps) on one torch thread when frames
        # render on several: its operations are small, and their intra-op threads' synchronisation is most of their
        # cost on a busy machine (the seen test of block_sliding_friction: 10 ms on one thread, 240 ms on two with
        # the load at 5 on the 2-core VM).
        before = torch.get_num_threads()
        if threads > 1:
            torch.set_num_threads(1)
        try:
            with torch.no_grad():
                poser = TexturedPoser(sim, camera, photo, backend=backend)
        finally:
            torch.set_num_threads(before)

    def work(a: int, b: int, done) -> None:
        with torch.no_grad():
            for k in range(a, b):
                if k > a and repeated[k]:  # at rest: the previous frame's render, bit for bit
                    rgb[k], alpha[k], depth[k] = rgb[k - 1], alpha[k - 1], depth[k - 1]
                    done(k)
                    continue
                g = poser.rest_gaussians if poser is not None and k == 0 else sim.gaussians_at(k)
                if poser is None:
                    out = rasterize(g.to(dev), camera, backend=backend)
                    rgb[k] = out.rgb.cpu()
                    alpha[k] = out.alpha.cpu()
                else:
                    feats, one = poser.features(k, g)
                    colors = None if poser.colors is None else poser.colors.to(dev, g.means.dtype)
                    out = rasterize(g.to(dev), camera, colors=colors, extra_features=feats.to(dev), backend=backend)
                    poser.shade(out, one, into=(rgb[k], alpha[k]))
                depth[k] = out.depth.cpu()
                done(k)

    run_frame_blocks(total, threads, work, progress, cost=[0 if r else 1 for r in repeated])
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
