"""Checks of a whole log file that several test areas share.

:func:`assert_log_times_monotonic` reads the file with the ``mcap`` library (an implementation
independent of ``dob_hil.log``), in file order, and checks that every channel's log time is
non-decreasing: a log-time-ordered reader (Foxglove, ``mcap``'s default iterator) then sees each
channel in the order it was written. :class:`CallClock` is a ``time_ns`` attribute computed by a
function, for ``LogWriter.clocked_frame_hook``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from mcap.reader import make_reader


def channel_log_times(path: Path) -> dict[str, list[int]]:
    """Every message's log time per topic, in file order."""
    times: dict[str, list[int]] = {}
    with path.open("rb") as f:
        reader = make_reader(f)
        for _schema, channel, message in reader.iter_messages(log_time_order=False):
            times.setdefault(channel.topic, []).append(message.log_time)
    return times


def assert_log_times_monotonic(path: Path) -> dict[str, list[int]]:
    """AssertionError naming the topic and the first step back; returns the times per topic."""
    times = channel_log_times(path)
    for topic, ts in times.items():
        back = next((i for i in range(1, len(ts)) if ts[i] < ts[i - 1]), None)
        assert back is None, (
            f"{path.name}: {topic} steps back at message {back}: {ts[back - 1]} -> {ts[back]} ns"  # type: ignore[operator]
        )
    return times


class CallClock:
    """A time source whose ``time_ns`` is ``now_ns()`` at each read."""

    def __init__(self, now_ns: Callable[[], int]) -> None:
        self._now_ns = now_ns

    @property
    def time_ns(self) -> int:
        return self._now_ns()
