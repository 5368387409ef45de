"""``replay --to-bus``: put a log's recorded frames back on a CAN bus with their original timing.

Frame i is sent at the absolute deadline ``start + (t_i - t_0)`` (its timestamp relative to the
first frame's; deadlines never drift with the time the sends themselves take). The thread sleeps
until ``spin_ns`` before each deadline (with the timer slack lowered where Linux allows), then
spins to it and sends: a plain sleep wakes 50-80 us late on Linux, and a late frame drags the
next ones into a burst. A frame whose deadline has passed is sent at once and counted late. The
report compares the most frequent id's inter-frame gap as recorded and as sent (median and p99).
Error frames cannot be transmitted and are
skipped (counted). Received copies of our own transmitted ids (udp_multicast delivers a process
its own frames, so such logs hold each command twice) are skipped too, so the bus sees each
frame once.

Caution: the recording holds the host's COMMAND frames; a live drive listening on the target bus
with the logged node id acts on them.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import can
import numpy as np
import numpy.typing as npt

from dob_hil.analysis.bus_usage import counted_frames
from dob_hil.analysis.frames import frame_messages
from dob_hil.analysis.metrics import distribution
from dob_hil.errors import DriveFault, LogReadError
from dob_hil.log.schemas import CAN_FLAG_ERROR

StructArray = npt.NDArray[np.void]
START_LEAD_NS = 5_000_000  # the first frame goes out this long after the start
MAX_GAP_NS = 60_000_000_000  # a longer silence between two recorded frames is a damaged log


@dataclass
class PlaybackStats:
    frames_sent: int
    skipped_error_frames: int
    skipped_own_echoes: int
    duration_s: float  # of the recording, first to last frame sent
    late_frames: int  # sent more than ``late_threshold_us`` after their deadline
    late_threshold_us: float
    lateness_us: dict[str, float | int] | None  # p50, p99, max, n
    gap_id: int | None = None  # the most frequent arbitration id
    recorded_gap_us: dict[str, float | int] | None = None  # its inter-frame gap as recorded
    sent_gap_us: dict[str, float | int] | None = None  # and as sent

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _set_timer_slack_1ns() -> None:
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(29, 1, 0, 0, 0)  # PR_SET_TIMERSLACK
    except (OSError, AttributeError):
        pass


def check_gaps(frames: StructArray, fd_frames: StructArray, max_gap_ns: int = MAX_GAP_NS) -> None:
    """LogReadError naming the first gap of more than ``max_gap_ns`` between consecutive frames."""
    stamps = np.sort(
        np.concatenate(
            [frames["timestamp_ns"].astype(np.uint64), fd_frames["timestamp_ns"].astype(np.uint64)]
        )
    )
    if len(stamps) < 2:
        return
    gaps = np.diff(stamps)
    at = np.flatnonzero(gaps > np.uint64(max_gap_ns))
    if len(at):
        i = int(at[0])
        raise LogReadError(
            f"replay --to-bus: frames {i} and {i + 1} (in time order) are {int(gaps[i]) / 1e9:.6g} s apart, "
            f"more than the {max_gap_ns / 1e9:g} s a recording can hold; refusing to replay this log"
        )


def play_frames(
    bus: can.BusABC,
    frames: StructArray,
    fd_frames: StructArray | None = None,
    *,
    clock_ns: Callable[[], int] = time.monotonic_ns,
    sleep: Callable[[float], None] = time.sleep,
    late_threshold_us: float = 1000.0,
    progress: Callable[[int, int], None] | None = None,
    spin_ns: int = 150_000,
    max_gap_ns: int = MAX_GAP_NS,
) -> PlaybackStats:
    """Send the frames onto ``bus`` at their recorded relative times (module docstring).
    Raises DriveFault when the bus refuses a frame, LogReadError (before sending anything) when
    two consecutive frames are more than ``max_gap_ns`` apart."""
    keep = counted_frames(frames) if len(frames) else np.zeros(0, dtype=bool)
    errors = int(np.count_nonzero((frames["flags"] & CAN_FLAG_ERROR) != 0))
    echoes = int(len(frames) - np.count_nonzero(keep) - errors)
    selected = frames[keep]
    fd = fd_frames if fd_frames is not None else frames[:0]
    check_gaps(selected, fd, max_gap_ns)
    total = len(selected) + len(fd)
    _set_timer_slack_1ns()
    lateness: list[int] = []
    sent_ns: list[int] = []
    ids: list[int] = []
    recorded_ns: list[int] = []
    first_ts: int | None = None
    last_ts = 0
    start_ns = clock_ns() + START_LEAD_NS
    for i, msg in enumerate(frame_messages(selected, fd)):
        ts_ns = round(msg.timestamp * 1e9)
        if first_ts is None:
            first_ts = ts_ns
        last_ts = ts_ns
        deadline = start_ns + (ts_ns - first_ts)
        remaining = deadline - clock_ns()
        if remaining > spin_ns:
            sleep((remaining - spin_ns) * 1e-9)
        now = clock_ns()
        while now < deadline:
            now = clock_ns()
        try:
            bus.send(msg)
        except can.CanError as exc:
            raise DriveFault(
                f"replay --to-bus: sending frame {i} (id 0x{msg.arbitration_id:X}) failed: {exc}"
            ) from exc
        lateness.append(now - deadline)
        sent_ns.append(now)
        ids.append(msg.arbitration_id)
        recorded_ns.append(ts_ns)
        if progress is not None and i % 4096 == 0:
            progress(i, total)
    late = np.asarray(lateness, dtype=np.int64)
    gap_id, recorded_gap, sent_gap = _gaps(np.asarray(ids), np.asarray(recorded_ns), np.asarray(sent_ns))
    return PlaybackStats(
        frames_sent=len(late),
        skipped_error_frames=errors,
        skipped_own_echoes=echoes,
        duration_s=(last_ts - first_ts) * 1e-9 if first_ts is not None else 0.0,
        late_frames=int(np.count_nonzero(late > late_threshold_us * 1e3)),
        late_threshold_us=late_threshold_us,
        lateness_us=distribution(late, 1e-3),
        gap_id=gap_id,
        recorded_gap_us=recorded_gap,
        sent_gap_us=sent_gap,
    )


def _gaps(
    ids: npt.NDArray[np.int64], recorded_ns: npt.NDArray[np.int64], sent_ns: npt.NDArray[np.int64]
) -> tuple[int | None, dict[str, float | int] | None, dict[str, float | int] | None]:
    """The most frequent id and its inter-frame gaps (us), recorded and as sent."""
    if len(ids) < 3:
        return None, None, None
    values, counts = np.unique(ids, return_counts=True)
    gap_id = int(values[np.argmax(counts)])
    mask = ids == gap_id
    if np.count_nonzero(mask) < 3:
        return gap_id, None, None
    return (
        gap_id,
        distribution(np.diff(recorded_ns[mask]), 1e-3),
        distribution(np.diff(sent_ns[mask]), 1e-3),
    )
