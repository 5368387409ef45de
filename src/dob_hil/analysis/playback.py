"""``replay --to-bus``: put a log's recorded frames back on a CAN bus with their original timing.

Frame i is sent at the absolute deadline ``start + (t_i - t_0)`` (its timestamp relative to the
first frame's; deadlines never drift with the time the sends themselves take). The thread sleeps
until ``spin_ns`` before each deadline (with the timer slack lowered where Linux allows), then
spins to it and sends: a plain sleep wakes 50-80 us late on Linux, and a late frame drags the
next ones into a burst. A frame whose deadline has passed is sent at once and counted late. The
report compares the most frequent id's inter-frame gap as recorded and as sent (median and p99).
Error frames cannot be transmitted and are skipped (counted). Received copies of our own
transmitted ids (udp_multicast delivers a process its own frames, so such logs hold each command
twice) are skipped too, so the bus sees each frame once: "our ids" are those the whole log holds
in the transmit direction, per channel (classic, FD), whatever ``direction`` selects, as
``dob-hil export`` decides.

Streamed, in memory independent of the log's length (:func:`play_log`): a survey pass finds our
transmitted ids; a plan pass, over the frames' times in send order, counts what will be sent
and skipped, refuses a gap of more than :data:`MAX_GAP_NS` between consecutive frames (before
any bus is opened) and finds the most frequent id; the playing pass sends. Each pass reads the
classic and the FD channel as separate streams (:func:`dob_hil.log.stream.open_stream`, a group
of chunks at a time) merged by timestamp with :func:`heapq.merge` (classic first on a tie; a
frame back in time within its channel, which only a foreign capture holds, goes where the file
holds it). The figures are accumulated as exact integer counts
(:class:`~dob_hil.analysis.int_distribution.IntCounts`: numpy's percentiles). :func:`play_frames`
plays frames held in arrays through the same code.

Caution: the recording holds the host's COMMAND frames; a live drive listening on the target bus
with the logged node id acts on them.
"""

from __future__ import annotations

import heapq
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from itertools import chain, islice
from operator import itemgetter
from pathlib import Path
from typing import Any, Protocol

import can
import numpy as np
import numpy.typing as npt

from dob_hil.analysis.frames import message_of_row
from dob_hil.analysis.int_distribution import IntCounts
from dob_hil.errors import DriveFault, LogReadError
from dob_hil.log.schemas import CAN_FLAG_ERROR, CAN_TX, TOPIC_CAN, TOPIC_CAN_FD
from dob_hil.log.stream import open_stream

StructArray = npt.NDArray[np.void]
START_LEAD_NS = 5_000_000  # the first frame goes out this long after the start
MAX_GAP_NS = 60_000_000_000  # a longer silence between two recorded frames is a damaged log
ROWS = 4096  # frames turned into Python rows at a time
FLUSH = 65536  # figures buffered per frame before they go into the counts
TOPICS = (TOPIC_CAN, TOPIC_CAN_FD)
FRAME_FIELDS = ("timestamp_ns", "arbitration_id", "direction", "dlc", "flags", "data")
_PLAN_FIELDS = ("timestamp_ns", "arbitration_id", "direction", "flags")


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


class FrameSource(Protocol):
    """Where the frames come from: one channel at a time, block by block."""

    warnings: list[str]

    def blocks(self, topic: str, names: tuple[str, ...] | None) -> Iterator[StructArray]:
        """The channel's frames in file order, restricted to ``names`` (None: every field)."""
        ...

    def both(self, names: tuple[str, ...]) -> Iterator[tuple[StructArray, StructArray]]:
        """The classic and the FD frames together, block by block (one pass over a log)."""
        ...


class LogFrames:
    """A log's frames, each pass a stream of groups of chunks; the reader's warnings, once each."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.warnings: list[str] = []

    def blocks(self, topic: str, names: tuple[str, ...] | None) -> Iterator[StructArray]:
        with open_stream(self.path, {topic: names}, events=False) as stream:
            for group in stream.blocks():
                yield group.frames if topic == TOPIC_CAN else group.fd_frames
            self._warn(stream.warnings)

    def both(self, names: tuple[str, ...]) -> Iterator[tuple[StructArray, StructArray]]:
        with open_stream(self.path, dict.fromkeys(TOPICS, names), events=False) as stream:
            for group in stream.blocks():
                yield group.frames, group.fd_frames
            self._warn(stream.warnings)

    def _warn(self, warnings: list[str]) -> None:
        self.warnings.extend(w for w in warnings if w not in self.warnings)


class ArrayFrames:
    """Frames held in arrays (classic, FD), served as blocks."""

    def __init__(self, frames: StructArray, fd_frames: StructArray | None) -> None:
        self._arrays = {TOPIC_CAN: frames, TOPIC_CAN_FD: fd_frames if fd_frames is not None else frames[:0]}
        self.warnings: list[str] = []

    def blocks(self, topic: str, names: tuple[str, ...] | None) -> Iterator[StructArray]:
        array = self._arrays[topic]
        for start in range(0, len(array), FLUSH):
            yield array[start : start + FLUSH]

    def both(self, names: tuple[str, ...]) -> Iterator[tuple[StructArray, StructArray]]:
        yield self._arrays[TOPIC_CAN], self._arrays[TOPIC_CAN_FD]


def transmitted_ids(source: FrameSource) -> dict[str, npt.NDArray[np.int64]]:
    """Per channel, the ids the log holds in the transmit direction (sorted)."""
    ids: dict[str, set[int]] = {topic: set() for topic in TOPICS}
    for blocks in source.both(("arbitration_id", "direction")):
        for topic, block in zip(TOPICS, blocks, strict=True):
            ids[topic].update(np.unique(block["arbitration_id"][block["direction"] == CAN_TX]).tolist())
    return {topic: np.asarray(sorted(ids[topic]), dtype=np.int64) for topic in TOPICS}


@dataclass
class _Selection:
    """Which frames are sent: the direction asked for, no error frames, none of our echoes."""

    direction: int | None  # CAN_RX, CAN_TX or None for both
    tx_ids: dict[str, npt.NDArray[np.int64]]

    def split(self, topic: str, block: StructArray) -> tuple[StructArray, npt.NDArray[np.bool_], int, int]:
        """(the block in the direction asked for, which of those are sent, errors, echoes)."""
        if self.direction is not None:
            block = block[block["direction"] == self.direction]
        error = (block["flags"] & CAN_FLAG_ERROR) != 0
        echo = ~error & (block["direction"] != CAN_TX) & np.isin(block["arbitration_id"], self.tx_ids[topic])
        return block, ~(error | echo), int(np.count_nonzero(error)), int(np.count_nonzero(echo))


class _GapCheck:
    """The first gap of more than ``max_gap_ns`` between consecutive frames, fed in send order
    (a frame back in time opens no gap: the gap is measured from the latest frame before it)."""

    def __init__(self, max_gap_ns: int) -> None:
        self.max_gap_ns = max_gap_ns
        self.n = 0
        self.latest: int | None = None
        self.found: tuple[int, int] | None = None  # (index of the frame after the gap, gap ns)

    def add(self, t: npt.NDArray[np.uint64]) -> None:
        if not len(t):
            return
        n, self.n = self.n, self.n + len(t)
        if self.found is not None:
            return
        start = t[:1] if self.latest is None else np.asarray([self.latest], dtype=np.uint64)
        latest = np.maximum.accumulate(np.concatenate([start, t]))  # [k]: the latest before frame k
        gaps = np.where(t > latest[:-1], t - latest[:-1], np.uint64(0))
        at = np.flatnonzero(gaps > np.uint64(self.max_gap_ns))
        if len(at):
            self.found = (n + int(at[0]), int(gaps[int(at[0])]))
        self.latest = int(latest[-1])

    def error(self) -> LogReadError | None:
        if self.found is None:
            return None
        i, gap = self.found[0] - 1, self.found[1]
        return LogReadError(
            f"replay --to-bus: frames {i} and {i + 1} (in time order) are {gap / 1e9:.6g} s apart, "
            f"more than the {self.max_gap_ns / 1e9:g} s a recording can hold; refusing to replay this log"
        )


@dataclass
class PlaybackPlan:
    """What the plan pass found (module docstring)."""

    frames: int = 0  # in the direction asked for, error frames and echoes included
    sent: int = 0
    errors: int = 0
    echoes: int = 0
    gap_id: int | None = None  # the most frequent id of those sent (the smallest of equals)
    gap_id_frames: int = 0
    refusal: LogReadError | None = None  # a gap too long: nothing may be sent
    selection: _Selection | None = field(default=None, repr=False)


Stamps = tuple[npt.NDArray[np.uint64], npt.NDArray[np.bool_]]  # timestamps, sent or not


def _stamps(
    topic: str, source: FrameSource, sel: _Selection, plan: PlaybackPlan, ids: Counter[int]
) -> Iterator[Stamps]:
    """One channel's (timestamps, sent) block by block; counts into ``plan`` and ``ids``."""
    for block in source.blocks(topic, _PLAN_FIELDS):
        chosen, sent, errors, echoes = sel.split(topic, block)
        plan.frames += len(chosen)
        plan.errors += errors
        plan.echoes += echoes
        values, counts = np.unique(chosen["arbitration_id"][sent], return_counts=True)
        ids.update(dict(zip(values.tolist(), counts.tolist(), strict=True)))
        if len(chosen):
            yield chosen["timestamp_ns"].astype(np.uint64), sent


def _head(t: npt.NDArray[np.uint64], horizon: int) -> int:
    """How many of ``t`` come before the first one later than ``horizon``."""
    over = np.flatnonzero(t > np.uint64(horizon))
    return int(over[0]) if len(over) else len(t)


def time_order(first: Iterator[Stamps], second: Iterator[Stamps]) -> Iterator[Stamps]:
    """Two channels' blocks (each in non-decreasing time) merged in time order, vectorised: each
    round passes on what neither channel can still precede (up to the earlier of the two last
    timestamps held). A frame back in time within its channel passes with its neighbours."""
    sources: list[Iterator[Stamps] | None] = [first, second]
    empty: Stamps = (np.zeros(0, np.uint64), np.zeros(0, np.bool_))
    held = [empty, empty]
    while True:
        for k in (0, 1):
            source = sources[k]
            while source is not None and not len(held[k][0]):
                got = next(source, None)
                if got is None:
                    sources[k] = source = None
                else:
                    held[k] = got
        if not len(held[0][0]) or not len(held[1][0]):  # one channel is done: the other passes
            if len(held[0][0]) or len(held[1][0]):
                yield held[0] if len(held[0][0]) else held[1]
            if sources[0] is None and sources[1] is None:
                return
            held = [empty, empty]
            continue
        (ta, sa), (tb, sb) = held
        horizon = min(int(ta[-1]), int(tb[-1]))
        ca, cb = _head(ta, horizon), _head(tb, horizon)
        if ca == cb == 0:  # only frames back in time stand in the way: the channel ending first passes
            ca, cb = (len(ta), 0) if int(ta[-1]) == horizon else (0, len(tb))
        t = np.concatenate([ta[:ca], tb[:cb]])
        sent = np.concatenate([sa[:ca], sb[:cb]])
        order = np.argsort(t, kind="stable")
        yield t[order], sent[order]
        held = [(ta[ca:], sa[ca:]), (tb[cb:], sb[cb:])]


def plan_playback(
    source: FrameSource, direction: int | None = None, max_gap_ns: int = MAX_GAP_NS
) -> PlaybackPlan:
    """The survey and plan passes (module docstring); a gap too long is in ``refusal``: checked
    over the frames in the direction asked for, then over those that will be sent."""
    sel = _Selection(direction, transmitted_ids(source))
    plan = PlaybackPlan(selection=sel)
    ids: Counter[int] = Counter()
    every, sent_only = _GapCheck(max_gap_ns), _GapCheck(max_gap_ns)
    classic, fd = (_stamps(topic, source, sel, plan, ids) for topic in TOPICS)
    for t, sent in time_order(classic, fd):
        every.add(t)
        sent_only.add(t[sent])
    plan.refusal = every.error() or sent_only.error()
    plan.sent = sent_only.n
    if ids:
        top = max(ids.values())
        plan.gap_id = min(i for i, n in ids.items() if n == top)
        plan.gap_id_frames = top
    return plan


def _rows(topic: str, source: FrameSource, sel: _Selection) -> Iterator[tuple[Any, ...]]:
    """One channel's frames to send, as rows (timestamp_ns, id, direction, dlc, flags, data)."""
    for block in source.blocks(topic, None):
        chosen, sent, _, _ = sel.split(topic, block)
        kept = chosen[sent]
        for start in range(0, len(kept), ROWS):
            part = kept[start : start + ROWS]
            yield from zip(*(part[name].tolist() for name in FRAME_FIELDS), strict=True)


class _Gaps:
    """Inter-frame gaps of one id, as integer counts, fed one frame at a time."""

    def __init__(self) -> None:
        self.counts = IntCounts()
        self._pending: list[int] = []
        self._last: int | None = None

    def append(self, value: int) -> None:
        self._pending.append(value)
        if len(self._pending) >= FLUSH:
            self.flush()

    def flush(self) -> None:
        if not self._pending:
            return
        values = np.asarray(
            self._pending if self._last is None else [self._last, *self._pending], dtype=np.int64
        )
        self.counts.add(np.diff(values))
        self._last = self._pending[-1]
        self._pending = []


def _set_timer_slack_1ns() -> None:
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(29, 1, 0, 0, 0)  # PR_SET_TIMERSLACK
    except (OSError, AttributeError):
        pass


def play(
    bus: can.BusABC,
    source: FrameSource,
    plan: PlaybackPlan,
    *,
    clock_ns: Callable[[], int] = time.monotonic_ns,
    sleep: Callable[[float], None] = time.sleep,
    late_threshold_us: float = 1000.0,
    progress: Callable[[int, int], None] | None = None,
    spin_ns: int = 150_000,
) -> PlaybackStats:
    """The playing pass: send what ``plan`` selected onto ``bus`` at the recorded relative times.
    Raises the plan's refusal before sending anything, DriveFault when the bus refuses a frame."""
    if plan.refusal is not None:
        raise plan.refusal
    assert plan.selection is not None
    sel = plan.selection
    total = plan.sent
    watch = plan.gap_id if total >= 3 and plan.gap_id_frames >= 3 else None
    recorded, sent_gaps = _Gaps(), _Gaps()
    lateness = IntCounts()
    pending: list[int] = []
    late_ns = late_threshold_us * 1e3
    late = 0
    merged = heapq.merge(*(_rows(topic, source, sel) for topic in TOPICS), key=itemgetter(0))
    head = list(islice(merged, 1))  # the streams are opened and their first groups read now
    _set_timer_slack_1ns()
    first_ts: int | None = None
    last_ts = 0
    start_ns = clock_ns() + START_LEAD_NS
    for i, row in enumerate(chain(head, merged)):
        msg = message_of_row(row, None)
        ts_ns: int = row[0]
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
        pending.append(now - deadline)
        if msg.arbitration_id == watch:
            recorded.append(ts_ns)
            sent_gaps.append(now)
        if len(pending) >= FLUSH:
            late += _flush_lateness(lateness, pending, late_ns)
            pending = []
        if progress is not None and i % 4096 == 0:
            progress(i, total)
    late += _flush_lateness(lateness, pending, late_ns)
    recorded.flush()
    sent_gaps.flush()
    return PlaybackStats(
        frames_sent=lateness.n,
        skipped_error_frames=plan.errors,
        skipped_own_echoes=plan.echoes,
        duration_s=(last_ts - first_ts) * 1e-9 if first_ts is not None else 0.0,
        late_frames=late,
        late_threshold_us=late_threshold_us,
        lateness_us=lateness.distribution(1e-3),
        gap_id=plan.gap_id if total >= 3 else None,
        recorded_gap_us=recorded.counts.distribution(1e-3) if watch is not None else None,
        sent_gap_us=sent_gaps.counts.distribution(1e-3) if watch is not None else None,
    )


def _flush_lateness(counts: IntCounts, pending: list[int], late_ns: float) -> int:
    values = np.asarray(pending, dtype=np.int64)
    counts.add(values)
    return int(np.count_nonzero(values > late_ns))


def play_log(bus: can.BusABC, path: Path, direction: int | None = None, **options: Any) -> PlaybackStats:
    """Plan and play the log at ``path`` (module docstring): the whole of it in bounded memory."""
    source = LogFrames(path)
    return play(bus, source, plan_playback(source, direction), **options)


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
    """Send frames held in arrays onto ``bus`` at their recorded relative times (module
    docstring; our transmitted ids are those of ``frames`` and ``fd_frames``). Raises DriveFault
    when the bus refuses a frame, LogReadError (before sending anything) when two consecutive
    frames are more than ``max_gap_ns`` apart."""
    source = ArrayFrames(frames, fd_frames)
    plan = plan_playback(source, None, max_gap_ns)
    return play(
        bus, source, plan, clock_ns=clock_ns, sleep=sleep, late_threshold_us=late_threshold_us,
        progress=progress, spin_ns=spin_ns,
    )  # fmt: skip
