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
