"""H.264 mp4 writing and reading with PyAV."""

from __future__ import annotations

import os
from fractions import Fraction
from pathlib import Path

import numpy as np
import torch

from .errors import InputError
from .fsutil import atomic_output


def _to_uint8_frames(frames) -> np.ndarray:
    if isinstance(frames, torch.Tensor):
        frames = frames.detach().cpu().float().numpy()
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


def write_mp4(path: str | os.PathLike, frames, fps: float = 24.0, crf: int = 18) -> Path:
    """Write (T,H,W,3) frames (float 0..1 or uint8) as H.264 yuv420p mp4, atomically.

    yuv420p needs even width and height: odd sizes are padded by one edge-replicated pixel
    (never cropped), so no image content is lost.
    """
    import av

    arr = _to_uint8_frames(frames)
    if not (0 < fps <= 1000):
        raise InputError(f"fps must be in (0, 1000]; got {fps}")
    t, h, w, _ = arr.shape
    ph, pw = h % 2, w % 2
    if ph or pw:
        arr = np.pad(arr, ((0, 0), (0, ph), (0, pw), (0, 0)), mode="edge")
    path = Path(path)
    rate = Fraction(fps).limit_denominator(1001)
    with atomic_output(path, suffix=".tmp.mp4") as tmp:
        with av.open(str(tmp), mode="w") as container:
            stream = container.add_stream("libx264", rate=rate)
            stream.width, stream.height = arr.shape[2], arr.shape[1]
            stream.pix_fmt = "yuv420p"
            stream.options = {"crf": str(int(crf)), "preset": "medium"}
            for frame in arr:
                for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                    container.mux(packet)
            for packet in stream.encode():
                container.mux(packet)
    return path


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
