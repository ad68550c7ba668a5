"""Memory available to a run, so heavy stages can refuse before they die of OOM."""

from __future__ import annotations

import os


def host_available_bytes() -> int:
    """Bytes of RAM available now (MemAvailable), or a conservative guess where unknown."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return 4 << 30


def device_available_bytes(device: str) -> int:
    if device.startswith("cuda"):
        try:
            import torch

            if torch.cuda.is_available():
                index = int(device.split(":")[1]) if ":" in device else torch.cuda.current_device()
                free, _ = torch.cuda.mem_get_info(index)
                return int(free)
        except Exception:  # noqa: BLE001 - fall through to warp's view
            pass
        try:
            import warp as wp

            from .warp_build import quiet_warp

            quiet_warp(wp)
            return int(wp.get_device(device).free_memory)
        except Exception:  # noqa: BLE001
            return 8 << 30
    return host_available_bytes()


def fmt_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"


def over_limit_message(need: float, have: float, fraction: float, where: str = "RAM") -> str:
    """"needs about X of RAM; Y is available and a run may use at most F % of it (Z), to leave room
    for the system and the other programs": what the limit really is, so a need below what is
    available but over the limit does not read as a contradiction."""
    return (f"needs about {fmt_bytes(need)} of {where}; {fmt_bytes(have)} is available now and a run may use at most "
            f"{fraction:.0%} of it ({fmt_bytes(fraction * have)}), to leave room for the system and other programs")


def check_device_fits(need_bytes: int, device, what: str, fraction: float = 0.95) -> None:
    """Refuse before moving ``need_bytes`` of model weights onto ``device`` when they cannot fit
    (on CUDA: the free memory now; on the CPU: the available RAM)."""
    from .errors import InputError

    dev = str(device)
    have = device_available_bytes(dev if dev.startswith("cuda") else "cpu")
    if need_bytes > fraction * have:
        where = "GPU memory" if dev.startswith("cuda") else "RAM"
        raise InputError(f"{what} (its weights alone, on {dev}) {over_limit_message(need_bytes, have, fraction, where)}. "
                         "Close other models (ComfyUI: unload models / --lowvram), or run this stage on the CPU.")


class oom_as_input_error:
    """Turn an out-of-memory failure inside the block into an InputError that says what to lower,
    instead of a traceback from deep inside torch (the models are offloaded by the caller's
    ``finally`` as usual)."""

    def __init__(self, what: str, advice: str):
        self.what, self.advice = what, advice

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc is None:
            return False
        import torch

        oom_types = tuple(t for t in (getattr(torch.cuda, "OutOfMemoryError", None),
                                      getattr(torch, "OutOfMemoryError", None)) if t is not None)
        is_oom = isinstance(exc, oom_types) or (isinstance(exc, (RuntimeError, MemoryError)) and (
            isinstance(exc, MemoryError) or "out of memory" in str(exc).lower()
            or "can't allocate memory" in str(exc).lower()))
        if not is_oom:
            return False
        from .errors import InputError

        try:
            torch.cuda.empty_cache()
        except Exception:  # noqa: BLE001
            pass
        raise InputError(f"{self.what} ran out of memory ({str(exc).splitlines()[0][:160]}). {self.advice}") from exc


# The up-front estimate of what a whole `generate` run adds to the process's memory (the pipeline
# checks it against free RAM before any work). Calibrated from measured peaks of RGBA cut-outs of
# several sizes and clip lengths (benchmarks/bench_memory.py, numbers in docs/reliability.md,
# "memory" section): a fixed part (simulation grid, Gaussians, rasterizer chunks, encoder), a part
# per pixel of the photo (loading, segmentation, inpainting, the silhouette lift's buffers) and a
# part per pixel per frame (rendered colour, alpha and depth, the composite, the encoder's input),
# times a safety margin.
# Fitted to the measurements (1365x1024 at 2 and 6 frames gives the per-frame part, 2048x1536 at 2
# frames the per-pixel part, the rest is fixed), rounded up; the margin covers what varies between
# runs and machines (allocator, thread count). The simulation's own share beyond the benchmark's
# grid is checked again by the simulator's estimate before its first substep.
# Recalibrated on a 2048x2048 cut-out at 2, 4 and 8 frames (issue 36): the per-frame part measured
# 52-57 bytes per pixel there (213-228 MiB per frame; the issue reported 197 MiB), above the 56 the
# smaller cut-outs gave, so it is 64 now: with the margin 80 bytes, 1.4x the largest measured slope,
# so a long clip of a large cut-out is refused before the machine swaps.
NEED_FIXED_BYTES = 512 << 20
NEED_BYTES_PER_PIXEL = 72
NEED_BYTES_PER_PIXEL_FRAME = 64
NEED_MARGIN = 1.25


def pipeline_need_bytes(width: int, height: int, frames: int) -> int:
    """Bytes a `generate` run on a ``width`` x ``height`` photo for ``frames`` frames is expected to
    add at its peak (see the constants above)."""
    px = int(width) * int(height)
    return int(NEED_MARGIN * (NEED_FIXED_BYTES + NEED_BYTES_PER_PIXEL * px
                              + NEED_BYTES_PER_PIXEL_FRAME * px * int(frames)))


def check_pipeline_fits(width: int, height: int, frames: int, what: str = "This video",
                        fraction: float = 0.8) -> None:
    """Refuse, before any work, a run whose estimated peak (``pipeline_need_bytes``) is over
    ``fraction`` of the RAM available now."""
    from .errors import InputError

    need, have = pipeline_need_bytes(width, height, frames), host_available_bytes()
    if need > fraction * have:
        per_frame = NEED_MARGIN * NEED_BYTES_PER_PIXEL_FRAME * int(width) * int(height)
        fit = max(int((fraction * have - pipeline_need_bytes(width, height, 0)) // max(per_frame, 1)), 0)
        raise InputError(f"{what} ({frames} frames of {width}x{height}) {over_limit_message(need, have, fraction)}. "
                         f"Lower the frame count (at most about {fit} at this size) or the image size (max_side / "
                         "--max-side, or scale the photo down), or free memory (close other programs or models).")
