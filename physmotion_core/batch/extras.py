"""Optional per-job outputs from other modules: point tracks and exact optical flow.

They come from ``physmotion_core.controls`` (point tracks, exact flow) when this version has it;
without it a job that asks for them still makes its video, and its manifest row says what was
skipped and why. Both are at the clip's own frames and rate (not resampled for a video model).
"""

from __future__ import annotations

import importlib
from pathlib import Path

_FUNCS = {"tracks": ("point_tracks",), "flow": ("exact_flow", "save_flow_npz")}


def _controls():
    try:
        return importlib.import_module("physmotion_core.controls")
    except ModuleNotFoundError as exc:
        if exc.name != "physmotion_core.controls":
            raise
        return None


def available(what: str) -> bool:
    mod = _controls()
    return mod is not None and all(hasattr(mod, f) for f in _FUNCS[what])


def write(what: str, res, out_dir: Path, points: int = 64) -> tuple[list[str], str]:
    """Write ``what`` (tracks / flow) of a finished generate() result into ``out_dir``.
    Returns (files written, relative to out_dir; the reason it was skipped, or '')."""
    if not available(what):
        return [], f"physmotion_core.controls.{' / '.join(_FUNCS[what])} is not in this version of physmotion"
    mod = _controls()
    out_dir = Path(out_dir)
    if what == "tracks":
        import numpy as np

        from ..fsutil import atomic_output

        tr = mod.point_tracks(res.sim, res.render, res.camera, num_points=int(points))
        with atomic_output(out_dir / "tracks.npz", suffix=".tmp.npz") as tmp:
            np.savez_compressed(tmp, uv=tr.uv.numpy().astype(np.float32), visible=tr.visible.numpy(),
                                particle=tr.particle.numpy(), width=np.int64(tr.width), height=np.int64(tr.height),
                                fps=np.float64(tr.fps),
                                convention=np.str_("uv[t, n] = (x, y) px, x right, y down, pixel centres at +0.5; "
                                                   "visible[t, n]: not behind the rendered surface"))
        return ["tracks.npz"], ""
    flow = mod.exact_flow(res.sim, res.camera)
    mod.save_flow_npz(out_dir / "flow.npz", flow, res.camera)
    return ["flow.npz"], ""
