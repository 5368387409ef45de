"""A one-line progress bar on stderr for long runs.

Drawn only when the stream is a terminal (never into a pipe or a file), only once a run has taken
``delay_s`` of wall time (a short run prints nothing), at most ``max_rate_hz`` times a second,
fitted to the terminal's width, with an ETA; :meth:`ProgressBar.finish` draws the final state
(100 % for a completed run) and ends the line.
"""

from __future__ import annotations

import shutil
import sys
import time
from collections.abc import Callable
from typing import TextIO


def _eta(seconds: float) -> str:
    seconds = max(0, round(seconds))
    if seconds >= 3600:
        return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m"
    return f"{seconds // 60}:{seconds % 60:02d}"


class ProgressBar:
    """``bar(done, total)`` as the run goes; ``bar.finish(done, total)`` at the end."""

    def __init__(
        self,
        label: str,
        enabled: bool = True,
        *,
        stream: TextIO | None = None,
        delay_s: float = 0.5,
        max_rate_hz: float = 10.0,
        clock: Callable[[], float] | None = None,
    ) -> None:
        self._stream = stream if stream is not None else sys.stderr
        self._label = label
        self._enabled = enabled and _is_terminal(self._stream)
        self._delay_s = delay_s
        self._interval_s = 1.0 / max_rate_hz
        self._clock = clock if clock is not None else time.perf_counter
        self._t0 = self._clock()
        self._last = -1.0
        self._drawn = False

    @property
    def enabled(self) -> bool:
        return self._enabled

    def line(self, done: int, total: int, elapsed_s: float, width: int) -> str:
        """The bar's text for ``done`` of ``total`` after ``elapsed_s``, at most ``width`` chars."""
        frac = min(1.0, done / total) if total > 0 else 1.0
        rate = done / elapsed_s if elapsed_s > 0 else 0.0
        tail = f" {100 * frac:5.1f}%"
        if done >= total:
            tail += f" {_eta(elapsed_s)} elapsed"
        elif rate > 0:
            tail += f" ETA {_eta((total - done) / rate)}"
        head = f"{self._label} "
        room = width - len(head) - len(tail) - 2
        if room < 10:  # a narrow terminal: drop the label, then shorten the bar
            head = ""
            room = max(0, width - len(tail) - 2)
        filled = int(room * frac)
        text = f"{head}[{'#' * filled}{'.' * (room - filled)}]{tail}"
        return text[: max(0, width)]

    def __call__(self, done: int, total: int) -> None:
        if not self._enabled:
            return
        now = self._clock()
        if now - self._t0 < self._delay_s or now - self._last < self._interval_s:
            return
        self._last = now
        self._draw(done, total, now - self._t0)

    def _draw(self, done: int, total: int, elapsed_s: float) -> None:
        width = shutil.get_terminal_size((80, 24)).columns - 1  # the last column would wrap
        self._stream.write("\r" + self.line(done, total, elapsed_s, width))
        self._stream.flush()
        self._drawn = True

    def finish(self, done: int | None = None, total: int | None = None) -> None:
        """Draw the final state (if the bar was ever drawn) and end its line."""
        if not (self._enabled and self._drawn):
            return
        if done is not None and total is not None:
            self._draw(done, total, self._clock() - self._t0)
        self._stream.write("\n")
        self._stream.flush()

    close = finish


def _is_terminal(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False
