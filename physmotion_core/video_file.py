"""A saved video file as a value with the interface of ComfyUI's ``VIDEO`` (``VideoInput``).

ComfyUI's native video nodes (Save Video, Get Video Components, ...) take a ``VideoInput``
(comfy_api, 0.3.64: ``comfy_api/latest/_input/video_types.py``), whose file-backed implementation is
``VideoFromFile``. Inside ComfyUI the nodes hand over that class itself; this module is the stand-in
when there is no ComfyUI (the CLI, tests), with the same methods: ``get_components()`` (frames as a
float [T,H,W,3] tensor in 0..1, the frame rate as a Fraction, audio), ``get_dimensions()``,
``get_duration()``, ``get_container_format()``, ``get_stream_source()`` and ``save_to(path, format,
codec, metadata)`` (a stream copy with the metadata added, as ``VideoFromFile.save_to`` does when the
format and codec are kept). The library never imports ComfyUI.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any, Optional

from .errors import InputError


@dataclass
class VideoComponents:
    """The parts of a video, as ComfyUI's ``VideoComponents``."""

    images: Any  # torch.Tensor [T,H,W,3] float in 0..1
    frame_rate: Fraction
    audio: Optional[dict] = None
    metadata: Optional[dict] = None


class VideoFile:
    """A video file on disk, read lazily."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(f"No video file at {self.path}")

    def __repr__(self) -> str:
        return f"VideoFile({str(self.path)!r})"

    def get_stream_source(self) -> str:
        return str(self.path)

    def _open(self):
        import av

        return av.open(str(self.path), mode="r")

    def get_dimensions(self) -> tuple[int, int]:
        with self._open() as c:
            s = c.streams.video[0]
            return int(s.width), int(s.height)

    def get_container_format(self) -> str:
        with self._open() as c:
            return c.format.name

    def get_components(self) -> VideoComponents:
        import numpy as np
        import torch

        with self._open() as c:
            s = c.streams.video[0]
            rate = Fraction(s.average_rate) if s.average_rate else Fraction(0)
            frames = [f.to_ndarray(format="rgb24") for f in c.decode(s)]
            metadata = dict(c.metadata)
        if not frames:
            raise InputError(f"{self.path} contains no video frames")
        images = torch.from_numpy(np.stack(frames)).float() / 255.0
        return VideoComponents(images=images, frame_rate=rate, audio=None, metadata=metadata)

    def get_duration(self) -> float:
        comp = self.get_components()
        return float(comp.images.shape[0] / comp.frame_rate) if comp.frame_rate else 0.0

    def save_to(self, path, format: str = "auto", codec: str = "auto", metadata: Optional[dict] = None) -> None:
        """Copy the streams into ``path`` (no re-encoding), adding ``metadata`` (values that are not
        strings are stored as JSON, as ComfyUI does with the prompt and workflow)."""
        import av

        fmt, cod = str(getattr(format, "value", format)), str(getattr(codec, "value", codec))
        with self._open() as src:
            names = src.format.name.split(",")
            vcodec = src.streams.video[0].codec_context.name if src.streams.video else None
            if fmt not in ("auto", *names) or cod not in ("auto", vcodec):
                raise InputError(f"{self.path.name} is {src.format.name}/{vcodec}; it can be saved as it is "
                                 f"(format/codec 'auto'), not converted to {fmt}/{cod}")
            options = {"movflags": "use_metadata_tags"} if "mp4" in names or "mov" in names else {}
            with av.open(str(path), mode="w", format=names[0] if "mp4" not in names else "mp4",
                         options=options) as out:
                for k, v in src.metadata.items():
                    if not metadata or k not in metadata:
                        out.metadata[k] = v
                for k, v in (metadata or {}).items():
                    out.metadata[k] = v if isinstance(v, str) else json.dumps(v)
                stream_map = {}
                for s in src.streams:
                    if s.type in ("video", "audio"):
                        stream_map[s] = out.add_stream_from_template(template=s, opaque=True)
                for packet in src.demux():
                    if packet.stream in stream_map and packet.dts is not None:
                        packet.stream = stream_map[packet.stream]
                        out.mux(packet)
