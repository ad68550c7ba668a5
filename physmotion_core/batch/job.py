"""One batch job, run inside a worker (a pool process or a Ray task): settings -> generate() -> files.

Nothing here raises across the process boundary: every outcome comes back as a plain dict,
``{"status": "done", ...}`` or ``{"status": "failed", "error": {...}}``. Only a worker that dies
(killed, out of memory, a crash in native code) shows up as an executor error, and that is what
the runner retries.
"""

from __future__ import annotations

import os
import platform
import shutil
import signal
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Optional

from ..fsutil import file_sha256

VIDEO = "video.mp4"


class EnvironmentMismatch(RuntimeError):
    """The worker's code or models differ from the driver's: its video would not be the job's video."""


def error_kind(exc: BaseException) -> str:
    """input / simulation / model / memory / environment / error (a bug). None of them is retried:
    the same job would fail the same way again."""
    from ..errors import InputError, MissingModelError, SimulationError

    if isinstance(exc, SimulationError):
        return "simulation"
    if isinstance(exc, MissingModelError):
        return "model"
    if isinstance(exc, InputError):
        return "input"
    if isinstance(exc, MemoryError):
        return "memory"
    if isinstance(exc, EnvironmentMismatch):
        return "environment"
    return "error"


def error_info(exc: BaseException, kind: Optional[str] = None) -> dict:
    info = {"kind": kind or error_kind(exc), "type": type(exc).__name__, "message": str(exc)}
    if info["kind"] == "error":
        info["traceback"] = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))[-4000:]
    return info


sha256_file = file_sha256  # the name the executors and the manifest use


def set_threads(threads: int) -> None:
    """Threads for everything in this worker: the simulator (PHYSMOTION_CPU_THREADS), torch (the
    CPU rasterizer), OpenMP/BLAS. Set before torch is imported where possible."""
    threads = max(1, int(threads))
    for var in ("PHYSMOTION_CPU_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(threads)
    if "torch" in sys.modules:
        import torch

        torch.set_num_threads(threads)


def worker_init(threads: int, gpu_slots=None, kernel_cache: Optional[str] = None) -> None:
    """Initializer of a local pool process. Ctrl-C goes to the driver only (it stops the pool); a
    SIGTERM from the driver unwinds the job, so atomic writers remove their temporary files."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    if kernel_cache:
        os.environ["WARP_CACHE_PATH"] = kernel_cache
    if gpu_slots is not None:
        os.environ["CUDA_VISIBLE_DEVICES"] = str(gpu_slots.get())
    set_threads(threads)
    import logging

    logging.getLogger("physmotion").addHandler(logging.NullHandler())  # warnings go to the job records
    import warp

    from ..warp_build import quiet_warp

    quiet_warp(warp)  # no start-up banner from every worker
    import torch  # noqa: F401 - imported here, once, with the thread settings in place

    torch.set_num_threads(max(1, int(threads)))


def warm_kernels(device: str = "cpu") -> dict:
    """Load (compiling on first use) the simulator's Warp module into Warp's on-disk kernel cache, so
    the workers that follow only load it. Returns the cache folder and the time it took."""
    t0 = time.perf_counter()
    from ..sim import kernels as K
    from ..sim.mpm import _warp

    wp = _warp()
    devices = ["cpu"]
    if device != "cpu" and wp.get_cuda_device_count() > 0:
        devices.append("cuda:0")
    for d in devices:
        wp.load_module(K, device=d)
    return {"kernel_cache": str(wp.config.kernel_cache_dir), "seconds": time.perf_counter() - t0,
            "devices": devices, "host": platform.node(), "pid": os.getpid()}


def _conditions(s: dict):
    from ..types.conditions import Conditions, Force, Ground, InitialVelocity, Region, Torque

    def region(at, radius):
        return Region() if at is None else Region.at_pixel(at[0], at[1], radius)

    conds = []
    if s["force"] is not None:
        conds.append(Force(tuple(s["force"]), region(s["force_at"], s["force_radius"]), *s["force_window"]))
    elif s["force_at"] is not None:
        from ..errors import InputError

        raise InputError("force_at needs force = [fx, fy, fz] (the push applied at that pixel)")
    for f in s["forces"]:
        conds.append(Force(tuple(f["vector"]), region(f["at"], f["radius"]), *f["window"]))
    if s["torque"] is not None:
        conds.append(Torque(tuple(s["torque"]), region(s["torque_at"], s["torque_radius"]), *s["torque_window"]))
    if s["velocity"] is not None or s["spin"] is not None:
        conds.append(InitialVelocity(tuple(s["velocity"] or (0.0, 0.0, 0.0)), tuple(s["spin"] or (0.0, 0.0, 0.0))))
    ground = None if s["ground"] == "none" else Ground(0.0, s["ground"], s["friction"])
    return Conditions(conds), ground


def build_inputs(s: dict) -> dict:
    """The generate() arguments of a job's normalised settings (raises InputError on bad values)."""
    from ..types.material import Material
    from ..types.settings import SimSettings

    from ..errors import InputError

    if not 0 <= s["crf"] <= 51:
        raise InputError(f"crf must be in [0, 51] (H.264 quality: 18 looks lossless, 23 is x264's default); got {s['crf']}")
    if not 1 <= s["encode_threads"] <= 64:
        raise InputError(f"encode_threads must be in [1, 64]; got {s['encode_threads']}")
    conds, ground = _conditions(s)
    params = {k: s[k] for k in ("E", "nu", "density") if s[k] is not None}
    params.update(s["material_params"])
    material = Material.preset(s["material"], **params)  # validates
    settings = SimSettings(frames=s["frames"], fps=s["fps"], grid_res=s["grid_res"], quality=s["quality"],
                           seed=s["seed"], device=s["device"])
    settings.validate()
    return {"conditions": conds, "ground": ground, "material": material, "settings": settings,
            "object_height": s["object_height"], "max_side": s["max_side"], "models": s["models"], "seed": s["seed"],
            "object_point": None if s["object_point"] is None else tuple(s["object_point"])}


def check_inputs(s: dict) -> Optional[dict]:
    """An error record if the settings cannot make a video (checked by the driver before any worker)."""
    try:
        build_inputs(s)
    except Exception as exc:  # noqa: BLE001 - recorded, the batch goes on
        return error_info(exc)
    return None


def _versions() -> dict:
    out = {"python": platform.python_version()}
    for mod in ("torch", "warp", "av"):
        m = sys.modules.get(mod)
        out[mod] = (getattr(m, "__version__", None) or getattr(getattr(m, "config", None), "version", None)) if m else None
    return out


def _summary_stats(stats: dict) -> dict:
    keep = ("device", "particles", "objects", "grid_res", "grid_dims", "dx", "substeps", "dt_min", "dt_max",
            "rest_from_frame", "mass_kg", "threads", "cpu_chunks", "launches", "wall_time_s", "kernel_load_s")
    out = {k: stats.get(k) for k in keep if k in stats}
    energy = stats.get("energy") or {}
    if energy:
        out["energy_final"] = {k: (v[-1] if v else None) for k, v in energy.items()}
        out["kinetic_max"] = max(energy.get("kinetic") or [0.0])
    return out


def run_job(task: dict, out_dir: Path) -> dict:
    """Make one job's outputs in ``out_dir`` (its own folder), each file written atomically. Returns
    the result record (without the driver's fields); never raises for a failed job."""
    from .spec import models_identity, physics_version

    t_start = time.perf_counter()
    s = task["settings"]
    out_dir = Path(out_dir)
    result = {"status": "failed", "host": platform.node(), "pid": os.getpid(), "attempt": task["attempt"]}
    marker = out_dir / ".running"
    if task.get("threads"):
        set_threads(task["threads"])
    # The library's warnings (a photo scaled down, a clamp) go into the job's record, not the console.
    import logging

    caught: list = []
    catcher = logging.Handler(logging.WARNING)
    catcher.emit = lambda rec: caught.append(f"{rec.levelname} {rec.name}: {rec.getMessage()}")
    lib_log = logging.getLogger("physmotion")
    lib_log.addHandler(catcher)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        marker.write_text(f"{os.getpid()} {task['attempt']}")
        if task.get("physics_version") and task["physics_version"] != physics_version():
            raise EnvironmentMismatch(f"this worker ({platform.node()}) runs physics {physics_version()}, the "
                                      f"driver {task['physics_version']}: install the same physmotion on every node")
        if task.get("models") is not None and models_identity(s["models"]) != task["models"]:
            raise EnvironmentMismatch(f"this worker ({platform.node()}) finds the models "
                                      f"{models_identity(s['models'])}, the driver {task['models']}: give every "
                                      "node the same $PHYSMOTION_MODELS")
        from ..pipeline import generate

        kwargs = build_inputs(s)
        mask = None
        if s["mask"] is not None:
            from ..image_io import load_image

            m_rgb, _ = load_image(task.get("mask_path") or s["mask"])
            mask = (m_rgb.mean(dim=-1) > 0.5).float()

        def stage(name):
            if task.get("_test_kill") and name == "render":
                # Test hook (tests/test_batch.py): the worker dies mid-job, as under the OOM killer.
                os.kill(os.getpid(), signal.SIGKILL)
            return None

        res = generate(task["image_path"], mask=mask, output=None, progress=stage, **kwargs)
        t_enc = time.perf_counter()
        # a fixed encoder thread count makes the mp4 reproducible (video.write_video: mbtree off too)
        from ..video import write_mp4

        write_mp4(out_dir / VIDEO, res.frames, fps=res.fps, crf=s["crf"], threads=max(1, int(s["encode_threads"])))
        res.timings["encode_s"] = time.perf_counter() - t_enc
        files = [VIDEO]
        outputs = task.get("outputs", {})
        t_out = time.perf_counter()
        if outputs.get("ply") == "rest":
            from ..ply import write_ply

            write_ply(out_dir / "gaussians.ply", res.gaussians)
            files.append("gaussians.ply")
        elif outputs.get("ply") == "sequence":
            from ..ply import write_ply_sequence

            seq = write_ply_sequence(out_dir / "ply", res.sim, every=outputs.get("ply_every", 1))
            files.extend(f"ply/{p.name}" for p in seq)
        skipped = {}
        from . import extras

        for what in ("tracks", "flow"):
            if outputs.get(what):
                made, why = extras.write(what, res, out_dir, points=outputs.get("tracks_points", 64))
                files.extend(made)
                if why:
                    skipped[what] = why
        if len(files) > 1:
            res.timings["outputs_s"] = time.perf_counter() - t_out  # .ply, tracks, flow
        result.update(status="done", files={f: {"sha256": sha256_file(out_dir / f), "bytes": (out_dir / f).stat().st_size}
                                            for f in files},
                      stats=_summary_stats(res.sim.stats), energy=res.sim.stats.get("energy"), stages=res.stages,
                      size=[int(res.frames.shape[2]), int(res.frames.shape[1])], frames=int(res.frames.shape[0]),
                      timings={k: round(v, 4) for k, v in res.timings.items()}, skipped=skipped)
    except Exception as exc:  # noqa: BLE001 - a failed job is a result, not a crash
        result["error"] = error_info(exc)
    finally:
        lib_log.removeHandler(catcher)
        try:
            marker.unlink()
        except OSError:
            pass
    if caught:
        result["warnings"] = caught[:50]
    result["versions"] = _versions()
    result["physics_version"] = physics_version()
    result["job_s"] = round(time.perf_counter() - t_start, 4)
    return result


def local_task(task: dict, out_dir: str) -> dict:
    """Pool entry point: write straight into the job's folder (the driver's disk)."""
    return run_job(task, Path(out_dir))


def remote_task(task: dict, image_bytes: bytes, mask_bytes: Optional[bytes] = None) -> dict:
    """Ray entry point: the image travels as bytes and the outputs come back as bytes, so the nodes
    of a cluster need no shared file system. The driver writes them (atomically) into OUT."""
    tmp = Path(tempfile.mkdtemp(prefix="physmotion-job-"))
    try:
        img = tmp / ("input" + task.get("image_suffix", ".png"))
        img.write_bytes(image_bytes)
        task = dict(task, image_path=str(img))
        if mask_bytes is not None:
            mpath = tmp / "mask.png"
            mpath.write_bytes(mask_bytes)
            task["mask_path"] = str(mpath)
        out = tmp / "out"
        result = run_job(task, out)
        if result["status"] == "done":
            result["payload"] = {f: (out / f).read_bytes() for f in result["files"]}
        return result
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
