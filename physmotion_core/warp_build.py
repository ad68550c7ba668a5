"""Building a module's Warp kernels once per process, on first use (shared by the compiled render and pose paths).

Warp is imported, told to be quiet and initialised only when a compiled path is first asked for, so that importing
the library costs nothing and a broken Warp install only turns those paths off.
"""

from __future__ import annotations

import functools
import threading
from typing import Callable, TypeVar

T = TypeVar("T")


def quiet_warp(wp) -> None:
    """Before Warp initialises: no banner and no per-module load lines in the user's output, warnings
    still shown. Warp before 1.10 reads ``config.quiet``; later ones read ``config.log_level``."""
    wp.config.quiet = True
    level = getattr(wp, "LOG_WARNING", None)
    if level is not None and hasattr(wp.config, "log_level"):
        wp.config.log_level = level


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

                quiet_warp(wp)
                wp.init()
                done.append(build(wp))
            return done[0]

    return get
