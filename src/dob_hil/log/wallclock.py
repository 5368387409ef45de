"""Putting a log's times on the wall clock, for tools that expect epoch time (BLF, ASC, python-can).

A run log keeps one clock per log: simulated time from 0 in lockstep, ``time.monotonic_ns`` in real
time. Its "run" metadata records the wall time at the start (``start_wall_time_ns``). The wall time
of a log time ``t`` is ``start_wall_time_ns + (t - t0)``, where ``t0`` is the log's earliest time:
exact in lockstep (t0 = 0 at the start), and within the start-up time (milliseconds) in real time.
A capture written by python-can's logger through :mod:`dob_hil.log.can_io` (mode "capture") is
already on the wall clock.
"""

from __future__ import annotations

from collections.abc import Mapping

CAPTURE_MODE = "capture"


def wall_offset_ns(metadata: Mapping[str, Mapping[str, str]], earliest_log_time_ns: int | None) -> int:
    """What to add to a log time to get epoch nanoseconds (0 for a capture or without metadata)."""
    run = metadata.get("run", {})
    if run.get("mode") == CAPTURE_MODE:
        return 0
    try:
        start_wall_ns = int(run["start_wall_time_ns"])
    except (KeyError, ValueError):
        return 0
    if not 0 < start_wall_ns < 2**63:
        return 0
    return start_wall_ns - (earliest_log_time_ns or 0)
