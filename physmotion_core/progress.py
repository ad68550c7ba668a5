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


# The live TextBar whose line is unfinished (at most one): ``end_line`` ends it before other output.
_OPEN: list = []


def end_line() -> None:
    """End a live progress bar's unfinished line, so that what is printed next starts a line of its own
    (the CLI calls it before its messages and log records)."""
    if _OPEN:
        bar = _OPEN.pop()
        bar.stream.write("\n")
        bar.stream.flush()


def duration_words(seconds: float) -> str:
    """A run time in words: "40 s", "12 min", "3.5 h"."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


#: The bar adds the time left once this share is done and this many seconds have passed (an estimate from the
#: pace so far).
ETA_AFTER = (0.01, 3.0)


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


class TextBar:
    """A plain text progress bar on stderr for the CLI (no extra dependency).

    On a terminal it redraws one line (``\r``); written to a file or a pipe (a log, CI) it prints a line
    of its own when the stage starts, at every quarter and at the end, instead of hundreds of redraws on
    one line. ``live`` forces either."""

    STEP = 0.25

    def __init__(self, label: str, stream=None, width: int = 30, live: Optional[bool] = None):
        # sys.stderr as it is now, not at import (a redirected or captured stream gets the bar)
        self.label, self.stream, self.width = label, sys.stderr if stream is None else stream, width
        self.live = _is_terminal(self.stream) if live is None else bool(live)
        self._start = time.monotonic()
        self._next = 0.0  # not live: the next fraction that gets a line
        self._ended = False
        self._drawn = 0  # live: the length of the line on the terminal now

    def __call__(self, done: int, total: int, preview=None) -> None:
        frac = min(max(done / max(total, 1), 0.0), 1.0)
        filled = int(frac * self.width)
        elapsed = time.monotonic() - self._start
        line = f"{self.label:<10} [{'#' * filled}{'.' * (self.width - filled)}] {frac * 100:5.1f}% {elapsed:6.1f}s"
        end = done >= total
        if not end and frac >= ETA_AFTER[0] and elapsed >= ETA_AFTER[1]:
            line += f", about {duration_words(elapsed * (1.0 - frac) / frac)} left"
        if self.live:  # blank out what a longer line before it left on the terminal
            line, self._drawn = line + " " * max(0, self._drawn - len(line)), len(line)
        if self.live:
            if _OPEN and _OPEN[0] is not self:
                end_line()  # another bar's line (a stage left unfinished by an error)
            self.stream.write("\r" + line)
            if end:
                self.stream.write("\n")
                _OPEN.clear()
            else:
                _OPEN[:] = [self]
        else:
            if self._ended or not (end or frac >= self._next):
                return
            self.stream.write(line + "\n")
            self._next = (int(frac / self.STEP + 1e-9) + 1) * self.STEP
            self._ended = end
        self.stream.flush()
