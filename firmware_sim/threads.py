"""The thread life cycle shared by the real-time simulated drives (native, several axes, CiA 402,
ODrive): daemon threads started once, one stop event, the first exception a thread hit re-raised
in the caller's thread by :meth:`DriveThreads.check` / :meth:`DriveThreads.stop`, and the
deadline wait of the timer threads (sleep, then spin the last ``spin_ns`` yielding on every turn,
so a thread of the same priority or another process on a shared CPU is never starved).

Simulated time is ``time.monotonic_ns() - _t0_ns`` with ``_t0_ns`` taken at :meth:`start`.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable

MAX_SLEEP_S = 0.05  # a timer thread notices stop() within this
JOIN_TIMEOUT_S = 5.0  # stop() waits this long for each thread (they are daemons)
yield_cpu = getattr(os, "sched_yield", lambda: time.sleep(0))


class DriveThreads:
    """Subclasses name their threads in :meth:`_thread_targets` and may act in :meth:`_on_start`
    (after ``_t0_ns`` is taken, before any thread runs)."""

    def __init__(self, *, spin_ns: int = 0) -> None:
        self.spin_ns = spin_ns
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._error: BaseException | None = None
        self._t0_ns = 0
        self._started = False

    def _thread_targets(self) -> tuple[tuple[str, Callable[[], None]], ...]:
        raise NotImplementedError

    def _on_start(self) -> None:
        """Called by :meth:`start` once ``_t0_ns`` is set, before the threads start."""

    def start(self) -> None:
        if self._started:
            raise RuntimeError("the real-time drive was already started")
        self._started = True
        self._t0_ns = time.monotonic_ns()
        self._on_start()
        for name, target in self._thread_targets():
            t = threading.Thread(target=self._guarded, args=(target,), name=name, daemon=True)
            self._threads.append(t)
            t.start()

    def stop(self) -> None:
        """Stop the threads (safe to call twice); re-raise an exception one of them hit."""
        self._stop.set()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(JOIN_TIMEOUT_S)  # bounded: a stop always returns (the threads are daemons)
        self.check()

    def check(self) -> None:
        """Re-raise, in the caller's thread, the exception a drive thread stopped on (if any)."""
        if self._error is not None:
            raise self._error

    @property
    def running(self) -> bool:
        return self._started and not self._stop.is_set()

    def _guarded(self, target: Callable[[], None]) -> None:
        try:
            target()
        except BaseException as exc:  # surfaced by check()/stop()
            if self._error is None:
                self._error = exc
            self._stop.set()

    def _wait_until(self, deadline_ns: int) -> bool:
        """Sleep (then spin, yielding, the last ``spin_ns``) until ``deadline_ns``; False if it had
        already passed (nothing waited)."""
        spin = self.spin_ns
        waited = False
        while not self._stop.is_set():
            remaining = deadline_ns - time.monotonic_ns()
            if remaining <= 0:
                return waited
            waited = True
            if remaining > spin:
                time.sleep(min((remaining - spin) * 1e-9, MAX_SLEEP_S))
            else:
                while time.monotonic_ns() < deadline_ns and not self._stop.is_set():
                    yield_cpu()  # never starve a thread of the same priority, nor hold the GIL
                return True
        return waited
