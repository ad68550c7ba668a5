"""Progress reporting and cancellation for long loops.

Library functions take ``progress: ProgressFn | None``. They call it as ``progress(done, total)``
(optionally ``preview=...``) often enough for Cancel to act within a second; the callback raises to
cancel (ComfyUI's interrupt exception in nodes, ``errors.Interrupted`` elsewhere).
"""

from __future__ import annotations

import sys
import time
from typing import Optional, Protocol


class ProgressFn(Protocol):
    def __call__(self, done: int, total: int, preview=None) -> None: ...


def report(progress: Optional[ProgressFn], done: int, total: int, preview=None) -> None:
    if progress is not None:
        if preview is None:
            progress(done, total)
        else:
            progress(done, total, preview=preview)


class Throttle:
    """Calls ``fn`` at most every ``interval`` seconds (and always on the final step)."""

    def __init__(self, fn: Optional[ProgressFn], interval: float = 0.1):
        self.fn, self.interval, self._last = fn, interval, 0.0

    def __call__(self, done: int, total: int, preview=None) -> None:
        if self.fn is None:
            return
        now = time.monotonic()
        if done >= total or now - self._last >= self.interval:
            self._last = now
            report(self.fn, done, total, preview)


def scaled(progress: Optional[ProgressFn], start: int, span: int, total: int) -> Optional[ProgressFn]:
    """Map a sub-stage's own (done, total) onto [start, start+span] of an overall total."""
    if progress is None:
        return None

    def fn(done: int, sub_total: int, preview=None) -> None:
        frac = done / max(sub_total, 1)
        report(progress, start + int(round(frac * span)), total, preview)

    return fn


class TextBar:
    """A plain text progress bar on stderr for the CLI (no extra dependency)."""

    def __init__(self, label: str, stream=None, width: int = 30):
        # sys.stderr as it is now, not at import (a redirected or captured stream gets the bar)
        self.label, self.stream, self.width = label, sys.stderr if stream is None else stream, width
        self._start = time.monotonic()
        self._last_len = 0

    def __call__(self, done: int, total: int, preview=None) -> None:
        frac = min(max(done / max(total, 1), 0.0), 1.0)
        filled = int(frac * self.width)
        elapsed = time.monotonic() - self._start
        line = f"\r{self.label:<10} [{'#' * filled}{'.' * (self.width - filled)}] {frac * 100:5.1f}% {elapsed:6.1f}s"
        self.stream.write(line)
        if done >= total:
            self.stream.write("\n")
        self.stream.flush()
