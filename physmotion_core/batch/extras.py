"""Optional per-job outputs from other modules: point tracks and optical flow.

They come from ``physmotion_core.controls`` (Wan tracks / control videos / exact flow) when this
version has it; without it a job that asks for them still makes its video, and its manifest row
says what was skipped and why.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from ..fsutil import atomic_output


def _controls():
    try:
        return importlib.import_module("physmotion_core.controls")
    except ModuleNotFoundError as exc:
        if exc.name not in ("physmotion_core.controls",):
            raise
        return None


def available(what: str) -> bool:
    mod = _controls()
    return mod is not None and hasattr(mod, _FUNCS[what])


_FUNCS = {"tracks": "tracks_from_simulation", "flow": "flow_from_simulation"}


def write(what: str, res, out_dir: Path) -> tuple[list[str], str]:
    """Write ``what`` (tracks / flow) for a finished generate() result into ``out_dir``.
    Returns (files written, relative to out_dir; the reason it was skipped, or '')."""
    mod = _controls()
    fn = getattr(mod, _FUNCS[what], None) if mod is not None else None
    if fn is None:
        return [], f"physmotion_core.controls.{_FUNCS[what]} is not in this version of physmotion"
    out_dir = Path(out_dir)
    if what == "tracks":
        import json

        tracks = fn(res.sim, res.camera, res.render)
        with atomic_output(out_dir / "tracks.json") as tmp:
            Path(tmp).write_text(tracks if isinstance(tracks, str) else json.dumps(tracks))
        return ["tracks.json"], ""
    import numpy as np

    flow = fn(res.sim, res.camera, res.render)
    with atomic_output(out_dir / "flow.npz", suffix=".tmp.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, flow=np.asarray(flow, dtype=np.float32))
    return ["flow.npz"], ""
