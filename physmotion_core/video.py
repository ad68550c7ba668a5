"""Video writing (mp4 / mov / mkv / webm / avi with PyAV, animated GIF with Pillow) and reading."""

from __future__ import annotations

import errno
import os
from fractions import Fraction
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from .errors import InputError
from .fsutil import atomic_output


def _to_uint8_frames(frames) -> np.ndarray:
    if isinstance(frames, torch.Tensor):
        frames = frames.detach().cpu()
        frames = frames.numpy() if frames.dtype == torch.uint8 else frames.float().numpy()
    arr = np.asarray(frames)
    if arr.ndim != 4 or arr.shape[-1] != 3:
        raise InputError(f"video frames must be (T, H, W, 3); got shape {arr.shape}")
    if arr.shape[0] == 0:
        raise InputError("cannot write a video with zero frames")
    if arr.dtype != np.uint8:
        if not np.all(np.isfinite(arr)):
            raise InputError("video frames contain NaN or Inf values")
        arr = (np.clip(arr, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return arr


#: Video containers by file extension: (PyAV format, codec, pixel format). Each gets a codec it
#: is made for: H.264 in mp4 / mov / mkv, VP9 in webm, MPEG-4 Part 2 in avi (what AVI players
#: expect), and an animated GIF (256-colour palette per frame, written by Pillow).
VIDEO_FORMATS = {
    ".mp4": ("mp4", "libx264", "yuv420p"),
    ".m4v": ("mp4", "libx264", "yuv420p"),
    ".mov": ("mov", "libx264", "yuv420p"),
    ".mkv": ("matroska", "libx264", "yuv420p"),
    ".webm": ("webm", "libvpx-vp9", "yuv420p"),
    ".avi": ("avi", "mpeg4", "yuv420p"),
    ".gif": ("gif", "gif", "pal8"),
}


def video_format(path: str | os.PathLike) -> tuple[str, str, str]:
    """(container, codec, pixel format) for ``path``'s extension; InputError for any other."""
    ext = Path(path).suffix.lower()
    if ext not in VIDEO_FORMATS:
        raise InputError(f"Cannot write a video as '{Path(path).name}': the extension "
                         f"{ext or '(none)'} is not a video format this writes. Use one of "
                         f"{', '.join(VIDEO_FORMATS)} (e.g. '{Path(path).stem or 'clip'}.mp4').")
    return VIDEO_FORMATS[ext]


#: x264's speed presets, fastest first (``write_video``'s ``preset``).
X264_PRESETS = ("ultrafast", "superfast", "veryfast", "faster", "fast", "medium", "slow", "slower", "veryslow")


def write_video(path: str | os.PathLike, frames, fps: float = 24.0, crf: int = 18,
                threads: Optional[int] = None, preset: str = "medium") -> Path:
    """Write (T,H,W,3) frames (float 0..1 or uint8) atomically, in the container its extension
    names (``VIDEO_FORMATS``); any other extension is refused before encoding.

    yuv420p needs even width and height: odd sizes are padded by one edge-replicated pixel
    (never cropped), so no image content is lost. ``crf`` is the quality (18: visually lossless
    H.264; mapped onto VP9's scale for webm; a bit rate for avi; unused for GIF). ``threads``: a
    fixed number of encoder threads, which makes H.264 files reproducible: the same frames give the
    same bytes in any process on any machine. Two things break that with libx264's defaults
    (measured with PyAV 18, x264 core 165: the same 80x64 frames encoded repeatedly in one process
    gave 2-4 different files): the automatic thread count, which x264 writes into the stream and
    slices frames by, and macroblock-tree rate control (mbtree), whose result depended on what the
    process had encoded before. So a fixed count also turns mbtree off (files a little larger at the
    same crf). None lets the encoder choose both (smallest files, bytes may vary). ``preset``: x264's speed
    preset for H.264 (``X264_PRESETS``; "ultrafast" encodes a node's preview clip about 3x faster than "medium",
    in a file about 2.5x larger at the same crf); the other codecs ignore it.
    """
    import av

    container_fmt, codec, pix_fmt = video_format(path)
    if preset not in X264_PRESETS:
        raise InputError(f"preset must be one of {', '.join(X264_PRESETS)}; got {preset!r}")
    arr = _to_uint8_frames(frames)
    if not (0 < fps <= 1000):
        raise InputError(f"fps must be in (0, 1000]; got {fps}")
    path = Path(path)
    if container_fmt == "gif":
        return _write_gif(path, arr, fps)
    t, h, w, _ = arr.shape
    ph, pw = h % 2, w % 2
    if ph or pw:
        arr = np.pad(arr, ((0, 0), (0, ph), (0, pw), (0, 0)), mode="edge")
    rate = Fraction(fps).limit_denominator(1001)
    with atomic_output(path, suffix=".tmp" + path.suffix.lower()) as tmp:
        with av.open(str(tmp), mode="w", format=container_fmt) as container:
            stream = container.add_stream(codec, rate=rate)
            stream.width, stream.height = arr.shape[2], arr.shape[1]
            stream.pix_fmt = pix_fmt
            if threads is not None:
                if int(threads) < 1:
                    raise InputError(f"threads must be a positive number of encoder threads; got {threads}")
                stream.codec_context.thread_count = int(threads)
            if codec == "libx264":
                stream.options = {"crf": str(int(crf)), "preset": preset,
                                  **({"threads": str(int(threads)), "x264-params": "mbtree=0"}
                                     if threads is not None else {})}
            elif codec == "libvpx-vp9":  # constant quality (b:v 0); VP9's 0..63 scale sits above x264's
                stream.options = {"crf": str(min(63, int(crf) + 13)), "b:v": "0", "deadline": "good",
                                  "cpu-used": "4", "row-mt": "1"}
            else:  # mpeg4: a bit rate that keeps crf 18's look (about 0.5 bit per pixel at 24 fps)
                bits_per_pixel = 0.5 * 2.0 ** ((18 - int(crf)) / 6.0)
                stream.bit_rate = int(min(80e6, max(1e6, bits_per_pixel * arr.shape[1] * arr.shape[2] * fps)))
            payload = 0  # bytes of encoded video handed to the muxer
            for frame in arr:
                for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                    payload += packet.size
                    container.mux(packet)
            for packet in stream.encode():
                payload += packet.size
                container.mux(packet)
        _check_complete(Path(tmp), path, payload, t)
    return path


def _check_complete(tmp: Path, target: Path, payload: int, frames: int) -> None:
    """FFmpeg's muxers do not report every failed write: on a disk that fills while a clip is
    encoded the container closes "successfully" around a cut-off file. So the file is checked
    before it is renamed into place: at least as many bytes as the encoder produced, and every
    frame readable back (the index that mp4 writes last is there). Otherwise it is removed and the
    error says whether the disk is full (and how much the clip needs)."""
    import av

    size = tmp.stat().st_size
    readable = 0
    if size >= payload:
        try:
            with av.open(str(tmp), mode="r") as c:
                readable = sum(1 for p in c.demux(c.streams.video[0]) if p.size)
        except (av.error.FFmpegError, OSError, IndexError):
            readable = 0
    if size >= payload and readable >= frames:
        return
    from .fsutil import disk_full_error, free_bytes

    free = free_bytes(tmp.parent)
    if free is not None and free < max(payload, 1 << 20):  # the disk is (nearly) full: that is why
        raise disk_full_error(target, size, OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)), need_bytes=payload)
    raise InputError(f"The video '{target}' came out incomplete ({size} bytes on disk for {payload} bytes of "
                     f"encoded video, {readable} of {frames} frames readable back): the write failed without an "
                     "error from the encoder. Check the disk and the folder, then run again; nothing was written "
                     "under that name.")


def _write_gif(path: Path, arr: np.ndarray, fps: float) -> Path:
    """An animated GIF that loops: each frame quantised to its own 256-colour palette. GIF delays
    are whole centiseconds, and players slow delays under 2 cs down, so fps above 50 is written at
    50 (logged)."""
    import logging

    from PIL import Image

    delay_cs = max(2, round(100.0 / fps))
    if abs(100.0 / delay_cs - fps) > 0.05 * fps:
        logging.getLogger("physmotion").warning(
            "GIF frame delays are whole hundredths of a second: %s plays at %.3g fps instead of %.3g; use .mp4 "
            "for the exact rate", path.name, 100.0 / delay_cs, fps)
    images = [Image.fromarray(f).quantize(256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
              for f in arr]
    with atomic_output(path, suffix=".tmp.gif") as tmp:
        images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=delay_cs * 10,
                       loop=0, optimize=False, disposal=1)
    return path


def write_mp4(path: str | os.PathLike, frames, fps: float = 24.0, crf: int = 18,
              threads: Optional[int] = None, preset: str = "medium") -> Path:
    """``write_video`` (the name is historical: the container follows ``path``'s extension, H.264
    mp4 for ``.mp4``)."""
    return write_video(path, frames, fps=fps, crf=crf, threads=threads, preset=preset)


def read_video(path: str | os.PathLike) -> tuple[np.ndarray, float]:
    """Decode a video into (T,H,W,3) uint8 RGB frames and its frame rate."""
    import av

    path = Path(path)
    if not path.is_file():
        raise InputError(f"No video file at {path}")
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        fps = float(stream.average_rate) if stream.average_rate else 0.0
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
    if not frames:
        raise InputError(f"{path} contains no video frames")
    return np.stack(frames), fps
