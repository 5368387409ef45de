"""One clock per log: the log times the session gives the events, frames and truth channels.

Lockstep: every channel is on the simulated clock (the sample instants ``k * period_ns`` of the
embedded drive); events raised with a host time (the link's receive time, a runner's clock) are
re-stamped with the drive's time. Real time: every channel is on ``time.monotonic_ns``, and each
channel's log time is kept non-decreasing (a frame's bus timestamp, the udp_multicast echo of our
own command, can be earlier than the frame logged before it; an event raised with an earlier
reading of the clock comes after one raised later): a time earlier than the channel's last is
logged at the last. In lockstep a sample's ``rx_time_ns``/``tx_time_ns`` are its simulated
instant too (the exchange takes no simulated time). Host wall-clock figures stay as fields
(``compute_ns``, the summary's ``wall_time_s``).

Real time, the frame hook only queues a frame with its time; the control thread packs the queued
frames at :meth:`LoopLog.flush`, after the period's command is sent. The embedded real-time
drive's ground truth arrives on its timer thread: it is queued here
(``collections.deque`` appends are thread-safe) and written by the control thread at its next
:meth:`LoopLog.flush`, so that the log writer has one owner.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

from dob_hil.log import LogWriter


class LoopLog:
    """The events channel (on the run's one clock) and the writer's flush, as the runners see them."""

    def __init__(self, log: LogWriter, sim_clock_ns: Callable[[], int] | None) -> None:
        self._log = log
        self._sim_clock_ns = sim_clock_ns
        self._last_event_ns = 0
        self._truth: deque[tuple[int, Any]] = deque()
        self._last_truth_ns = 0
        self._frames: list[Any] = []
        self._write_frames: Callable[[], None] | None = None

    def defer_frames(self, pending: list[Any], write: Callable[[], None]) -> None:
        """Frames queued by the frame hook (``pending``) are written by ``write`` at each flush."""
        self._frames, self._write_frames = pending, write

    def now_ns(self) -> int:
        """The run's clock: the drive's simulated time in lockstep, monotonic in real time."""
        sim = self._sim_clock_ns
        return sim() if sim is not None else time.monotonic_ns()

    def event(
        self, time_ns: int | None, level: str, kind: str, message: str, data: Mapping[str, Any] | None = None
    ) -> None:
        """An event at ``time_ns`` (None: now); in lockstep always at the drive's time."""
        sim = self._sim_clock_ns
        t = sim() if sim is not None else (time.monotonic_ns() if time_ns is None else time_ns)
        t = max(t, self._last_event_ns)
        self._last_event_ns = t
        self._log.event(t, level, kind, message, data)

    def queue_truth(self, t: Any) -> None:
        """Real time, from the drive's thread: keep the truth tuple for the control thread."""
        self._truth.append((time.monotonic_ns(), t))

    def flush(self, force: bool = False) -> None:
        """Write what the hooks queued (frames, truth), then let the writer hand over its batch."""
        if self._frames and self._write_frames is not None:
            self._write_frames()
        if self._truth:
            self.drain_truth()
        self._log.flush(force)

    def drain_truth(self) -> None:
        pending, write = self._truth, self._log.truth
        last = self._last_truth_ns
        while pending:
            stamp_ns, (period_index, _drive_ns, state, disturbance_A, applied_A, drive_state) = (
                pending.popleft()
            )
            last = stamp_ns if stamp_ns > last else last
            if type(disturbance_A) is not tuple:  # one drive; a multi-axis drive gives one per input
                disturbance_A, applied_A = (disturbance_A,), (applied_A,)
            write(last, state, disturbance_A, applied_A, period_index, drive_state)
        self._last_truth_ns = last


def frame_clamp() -> Callable[[int], int]:
    """A per-channel non-decreasing filter of log times (real-time frames)."""
    last = [0]

    def clamp(t: int) -> int:
        if t < last[0]:
            return last[0]
        last[0] = t
        return t

    return clamp
