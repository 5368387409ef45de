"""The control-thread side of the live view: a decimating, never-blocking tap on the log writer.

:class:`TappedLogWriter` is the run's :class:`~dob_hil.log.writer.LogWriter` with three methods
extended: every ``decimation``-th sample and ground-truth record, and every event, are also handed
to the live-server process through a non-blocking pipe (:class:`LiveTap`). When the pipe is full
(the live process is behind) the item is dropped and counted; the loop never waits for the
viewer. The MCAP log keeps every record.

A forwarded record is packed into the same CDR message the log holds (:mod:`dob_hil.live.packing`)
and written as bytes, so the control thread pays a counter per record and one pack and one
``write`` per forwarded record, and the live process deserialises nothing.
"""

from __future__ import annotations

import json
import os
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

from dob_hil.live.packing import KIND_EVENT, KIND_SAMPLE, KIND_TRUTH, Packer
from dob_hil.log import LogWriter

PIPE_ATOMIC_BYTES: Final = 4096  # PIPE_BUF on Linux: a write this size is never split
_HEAD: Final = struct.Struct("!i")  # multiprocessing.Connection's message header
EVENT_TEXT_CHARS: Final = 1000  # an event's message and data JSON are cut to fit one atomic write


@dataclass
class TapStats:
    forwarded: int = 0  # items written to the pipe
    dropped: int = 0  # items the full (or closed) pipe refused

    def as_dict(self) -> dict[str, int]:
        return {"forwarded": self.forwarded, "dropped": self.dropped}


def decimation_for(period_ns: int, rate_hz: float) -> int:
    """Every how many-th sample to forward so that about ``rate_hz`` reach the viewer (>= 1)."""
    if not rate_hz > 0:
        raise ValueError(f"live rate: must be > 0 Hz, got {rate_hz}")
    return max(1, round(1e9 / (period_ns * rate_hz)))


class LiveTap:
    """Writes items to a non-blocking pipe (``fd``, the sending end of a ``multiprocessing.Pipe``)
    as ``Connection`` messages: a 4-byte length and the frame, in one write of at most
    ``PIPE_BUF`` bytes, which the kernel either takes whole or refuses (``EAGAIN``: dropped and
    counted). No thread of ours is involved (a ``multiprocessing.Queue`` would wake its feeder
    thread, which takes the GIL from the loop, for every item)."""

    def __init__(self, fd: int, decimation: int) -> None:
        if decimation < 1:
            raise ValueError(f"live decimation: must be >= 1, got {decimation}")
        os.set_blocking(fd, False)
        self._fd = fd
        self.decimation = decimation
        self.stats = TapStats()

    def put(self, frame: bytes) -> None:
        """One frame (:mod:`dob_hil.live.packing`) as one ``Connection`` message, or a drop."""
        if len(frame) + _HEAD.size > PIPE_ATOMIC_BYTES:
            self.stats.dropped += 1
            return
        try:
            os.write(self._fd, _HEAD.pack(len(frame)) + frame)
        except OSError:  # BlockingIOError: the pipe is full; BrokenPipeError: the server is gone
            self.stats.dropped += 1
        else:
            self.stats.forwarded += 1


def _cut(text: str) -> str:
    return text if len(text) <= EVENT_TEXT_CHARS else text[: EVENT_TEXT_CHARS - 3] + "..."


_log_sample = LogWriter.sample
_log_truth = LogWriter.truth


class TappedLogWriter(LogWriter):
    """A :class:`LogWriter` that also feeds a :class:`LiveTap` (decimated samples and truth, all
    events). Same arguments as :class:`LogWriter`, plus ``tap``."""

    def __init__(self, *args: Any, tap: LiveTap, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.tap = tap
        self._live_frame = Packer(self.layout).frame
        self._live_every = tap.decimation
        self._live_sample_left = 1  # the first sample goes out at once
        self._live_truth_left = 1
        self._live_last_event_ns = 0

    def sample(self, *args: Any) -> None:  # the 18 arguments of LogWriter.sample
        _log_sample(self, *args)  # the plain function: no super() object per sample
        left = self._live_sample_left - 1
        if left:
            self._live_sample_left = left
            return
        self._live_sample_left = self._live_every
        self._forward(KIND_SAMPLE, args)

    def truth(self, *args: Any) -> None:  # the 6 arguments of LogWriter.truth
        _log_truth(self, *args)
        left = self._live_truth_left - 1
        if left:
            self._live_truth_left = left
            return
        self._live_truth_left = self._live_every
        self._forward(KIND_TRUTH, args)

    def event(
        self, time_ns: int, level: str, kind: str, message: str, data: Mapping[str, Any] | None = None
    ) -> None:
        super().event(time_ns, level, kind, message, data)
        self._live_last_event_ns = max(self._live_last_event_ns, int(time_ns))
        data_json = _cut(json.dumps(dict(data or {}), default=str))
        self._forward(KIND_EVENT, (int(time_ns), level, kind, _cut(message), data_json))

    def _forward(self, kind: int, args: tuple[Any, ...]) -> None:
        try:
            frame = self._live_frame(kind, args)
        except ValueError:  # cannot happen for a record the log took; never the loop's problem
            self.tap.stats.dropped += 1
            return
        self.tap.put(frame)

    def close(self, summary: Mapping[str, Any] | None = None, timeout_s: float = 60.0) -> None:
        """Note in the log how many live items were forwarded and dropped, then close it."""
        if not self.closed:
            s = self.tap.stats
            super().event(
                self._live_last_event_ns, "info", "live_stats",
                f"live view: {s.forwarded} items forwarded, {s.dropped} dropped (pipe full)",
                s.as_dict(),
            )  # fmt: skip
        super().close(summary, timeout_s)
