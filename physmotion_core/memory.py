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


def check_device_fits(need_bytes: int, device, what: str, fraction: float = 0.95) -> None:
    """Refuse before moving ``need_bytes`` of model weights onto ``device`` when they cannot fit
    (on CUDA: the free memory now; on the CPU: the available RAM)."""
    from .errors import InputError

    dev = str(device)
    have = device_available_bytes(dev if dev.startswith("cuda") else "cpu")
    if need_bytes > fraction * have:
        where = "GPU memory" if dev.startswith("cuda") else "RAM"
        raise InputError(f"{what} needs about {fmt_bytes(need_bytes)} of {where} for its weights alone but only "
                         f"{fmt_bytes(have)} is free on {dev}. Close other models (ComfyUI: unload models / "
                         "--lowvram), or run this stage on the CPU.")


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
