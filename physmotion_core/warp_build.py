"""Building a module's Warp kernels once per process, on first use (shared by the compiled render and pose paths).

Warp is imported, told to be quiet and initialised only when a compiled path is first asked for, so that importing
the library costs nothing and a broken Warp install only turns those paths off.
"""

from __future__ import annotations

import functools
import logging
import os
import sys
import tempfile
import threading
from typing import Callable, TypeVar

log = logging.getLogger("physmotion")

T = TypeVar("T")


def quiet_warp(wp) -> None:
    """Before Warp initialises: no banner and no per-module load lines in the user's output, warnings
    still shown. Warp before 1.10 reads ``config.quiet``; later ones read ``config.log_level``."""
    wp.config.quiet = True
    level = getattr(wp, "LOG_WARNING", None)
    if level is not None and hasattr(wp.config, "log_level"):
        wp.config.log_level = level


#: Warp's C library prints this to the process's stderr on every start on a machine without an NVIDIA driver
#: (a CPU machine: nothing is wrong). The CLI, which owns its stderr, hides it (``hide_no_driver_warning``);
#: inside ComfyUI or another program, whose other threads share that stderr, it is left alone.
NO_DRIVER_LINE = "Could not find or load the NVIDIA CUDA driver"
_hide_no_driver = False


def hide_no_driver_warning(on: bool = True) -> None:
    """Have ``init_warp`` hide Warp's no-driver line (and say it at INFO instead): for the CLI."""
    global _hide_no_driver
    _hide_no_driver = bool(on)


def init_warp(wp) -> None:
    """``quiet_warp`` and ``wp.init()``; with ``hide_no_driver_warning`` on, what Warp's C library writes to
    stderr while it starts is caught and passed on, all but the no-driver line."""
    quiet_warp(wp)
    if not _hide_no_driver:
        wp.init()
        return
    with tempfile.TemporaryFile() as caught:
        sys.stderr.flush()
        saved = os.dup(2)
        try:
            os.dup2(caught.fileno(), 2)
            wp.init()
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            caught.seek(0)
            for line in caught.read().decode("utf-8", "replace").splitlines():
                if NO_DRIVER_LINE in line:
                    log.info("Warp found no NVIDIA CUDA driver: simulating on the CPU")
                elif line.strip():
                    sys.stderr.write(line + "\n")
            sys.stderr.flush()


def built_once(build: Callable[..., T]) -> Callable[[], T]:
    """Decorator: ``build(wp)`` defines a module's Warp functions and kernels and returns them; the decorated
    function, called with no arguments, imports and initialises Warp and runs ``build`` on its first call, and
    returns that same result on every later one (one build per process, under a lock; a build that raises is
    tried again on the next call)."""
    lock = threading.Lock()
    done: list = []

    @functools.wraps(build)
    def get() -> T:
        with lock:
            if not done:
                import warp as wp

                init_warp(wp)
                done.append(build(wp))
            return done[0]

    return get
