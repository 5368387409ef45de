"""The metrics of a log of any length in bounded memory: streamed over groups of chunks.

:func:`analyze_streamed` gives the dictionary of :func:`dob_hil.analysis.metrics.compute_metrics`
without holding the log: memory is that of a few groups of chunks (:mod:`dob_hil.log.stream`),
whatever the log's length. Two passes over the file:

1. the *survey* reads a few fields: sample count, first instant and window start, the clocks
   the bus load needs (the first 1024 samples, 4096 evenly spread ones, the smallest transmitted
   frame stamps, the transmitted ids), the truth records' period indexes (consecutive: two
   integers; otherwise the indexes are kept, 4 B per record), the feedback/sequence histogram of
   the truth match, the events, and what :func:`dob_hil.analysis.loaded.interpret` needs;
2. the *metrics pass* reads the analysis fields and feeds every window sample to accumulators:
   sums of squares and maxima per output column (tracking, disturbance, estimation), flag
   counts, sequence gaps (carrying the previous sample across blocks), timing distributions
   (:class:`~dob_hil.analysis.int_distribution.IntCounts`: exact percentiles, as numpy's), and
   the bus frames of the window (frames within 1 s of the window's ends are kept until the
   clock offset is final).

Ground truth is joined to the samples as it streams by (truth rows are buffered until the samples
that want them arrive; samples wait for their truth rows at most ``MAX_PENDING`` groups, after which
a sample without its row counts as unmatched, with a warning naming how many). The truth offset of
:func:`dob_hil.analysis.truth_match.match_truth` is first assumed to be the lockstep convention (0),
and checked on the same 64 samples ``match_truth`` scores; only when that check fails (a real-time
log) is the offset searched in a pass over the truth records and the metrics pass run again with it.
The bus clock offset is refined as :func:`dob_hil.analysis.bus_usage.clock_offset_ns` does; should
it move by more than the 1 s margin, the frames are counted again in a pass of their own.

The figures are those of the in-memory path; sums are accumulated block by block, so sums of
squares (RMS) may differ from the in-memory ones in the last bits; counts, maxima and
percentiles are identical.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from dob_hil.analysis.bus_usage import _WORST, _offset_against, frame_classes, load_figures
from dob_hil.analysis.int_distribution import IntCounts
from dob_hil.analysis.loaded import ANALYSIS_FIELDS, LoadedLog, SampleSummary, interpret
from dob_hil.analysis.metrics import (
    WindowFigures,
    _covered_below,
    assemble_metrics,
    first_at_or_after,
    non_finite_rows,
    out_of_sequence,
)
from dob_hil.analysis.rerun import skipped_ranges
from dob_hil.analysis.signals import encoder_quantum
from dob_hil.analysis.truth_match import SCORE_SAMPLES, _Index
from dob_hil.log.schemas import (
    CAN_FLAG_ERROR,
    CAN_TX,
    FLAG_DOB_ON,
    FLAG_FEEDBACK_MISSING,
    FLAG_OVERRUN,
    FLAG_SATURATED,
    TOPIC_CAN,
    TOPIC_CAN_FD,
    TOPIC_SAMPLE,
    TOPIC_TRUTH,
)
from dob_hil.log.stream import Blocks, open_stream, return_large_buffers_to_the_os

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]
StructArray = npt.NDArray[np.void]

HEAD_SAMPLES: Final = 1024  # bus_usage pairs the first 1024 samples ...
HEAD_TX_FRAMES: Final = 1024 + 64  # ... with the smallest transmitted stamps, 64 shifts
BUS_PICKS: Final = 4096  # samples that refine the bus clock offset
MARGIN_NS: Final = 1_000_000_000  # frames this near the window's ends wait for the final offset
CLOCKS: Final = ("time_ns", "tx_time_ns")
MAX_PENDING: Final = 8  # groups of samples waiting for their truth rows, at most
_INT64_MAX: Final = np.uint64(2**63 - 1)

SURVEY_FIELDS: Final[dict[str, tuple[str, ...] | None]] = {
    TOPIC_SAMPLE: ("time_ns", "tx_time_ns", "seq", "feedback_seq", "flags"),
    TOPIC_TRUTH: ("period_index",),
    TOPIC_CAN: ("timestamp_ns", "direction", "arbitration_id"),
    TOPIC_CAN_FD: ("timestamp_ns",),
}
METRICS_FIELDS: Final[dict[str, tuple[str, ...] | None]] = {
    **ANALYSIS_FIELDS,
    TOPIC_CAN_FD: ("timestamp_ns",),
}


def _i64(values: npt.NDArray[Any]) -> IntArray:
    """uint64 stamps as int64, clipped (ordering against any int64 bound is kept)."""
    return np.asarray(np.minimum(values, _INT64_MAX), dtype=np.int64)


def _spread(n: int, count: int) -> IntArray:
    return np.linspace(0, n - 1, min(count, n)).astype(np.int64) if n else np.zeros(0, np.int64)


class _Picks:
    """Values of some columns at given global sample indexes, collected as blocks stream by."""

    def __init__(self, indexes: IntArray, names: tuple[str, ...]) -> None:
        self.indexes = indexes
        self.values = {name: np.zeros(len(indexes), dtype=np.int64) for name in names}

    def take(self, block: StructArray, g0: int) -> None:
        lo, hi = np.searchsorted(self.indexes, [g0, g0 + len(block)])
        if hi > lo:
            local = self.indexes[lo:hi] - g0
            for name, out in self.values.items():
                out[lo:hi] = block[name][local].astype(np.int64)


# ---------------------------------------------------------------------------------- survey
@dataclass
class Survey:
    """Pass 1 (module docstring)."""

    from_s: float
    n: int = 0
    t0: int = 0
    first: int | None = None  # window start (global sample index); None: past the end
    before_first: dict[str, int] = field(default_factory=dict)  # the clocks at first - 1
    last: dict[str, int] = field(default_factory=dict)  # the clocks of the last sample
    head: dict[str, list[IntArray]] = field(default_factory=lambda: {c: [] for c in CLOCKS})
    head_n: int = 0
    picks: _Picks | None = None
    tx_smallest: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    n_frames: int = 0
    n_tx: int = 0
    tx_ids: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    truth_n: int = 0
    truth_first: int = 0
    truth_last: int = 0
    truth_consecutive: bool = True
    truth_keys: list[IntArray] = field(default_factory=list)  # kept only while not consecutive
    n_valid: int = 0
    fb_offsets: IntArray = field(default_factory=lambda: np.zeros(256, np.int64))
    seq_min: int = 0
    seq_max: int = 0
    dob_on: int = 0
    time_back: int = 0  # time steps that go back (metrics.time_steps_back)
    spacing: IntCounts = field(default_factory=IntCounts)
    events: list[dict[str, Any]] = field(default_factory=list)

    def add(self, b: Blocks) -> None:
        self.events.extend(b.events)
        self._samples(b.samples)
        self._truth(b.truth)
        self._frames(b.frames)

    def _samples(self, s: StructArray) -> None:
        if len(s) == 0:
            return
        g0 = self.n
        t_ns = s["time_ns"].view(np.int64)
        if g0 == 0:
            self.t0 = int(t_ns[0])
        clocks = {name: s[name].astype(np.int64) for name in CLOCKS}
        if self.first is None:
            t_s = (t_ns - self.t0) * 1e-9
            i = first_at_or_after(t_s, self.from_s)
            if i < len(s):
                self.first = g0 + i
                for name, c in clocks.items():
                    if i > 0:
                        self.before_first[name] = int(c[i - 1])
                    elif g0 > 0:
                        self.before_first[name] = self.last[name]
        positive = np.diff(np.concatenate([[self.last["time_ns"]], t_ns]) if g0 else t_ns)
        self.spacing.add(positive[positive > 0])
        self.time_back += int(np.count_nonzero(positive < 0))
        if self.head_n < HEAD_SAMPLES:
            take = min(HEAD_SAMPLES - self.head_n, len(s))
            for name, c in clocks.items():
                self.head[name].append(c[:take])
            self.head_n += take
        if self.picks is not None:
            self.picks.take(s, g0)
        for name, c in clocks.items():
            self.last[name] = int(c[-1])
        self.last["time_ns"] = int(t_ns[-1])
        seq = s["seq"].astype(np.int64)
        valid = (s["flags"] & FLAG_FEEDBACK_MISSING) == 0
        self.n_valid += int(np.count_nonzero(valid))
        self.fb_offsets += np.bincount(
            (s["feedback_seq"][valid].astype(np.int64) - seq[valid]) % 256, minlength=256
        )
        lo, hi = int(seq.min()), int(seq.max())
        self.seq_min, self.seq_max = (lo, hi) if g0 == 0 else (min(self.seq_min, lo), max(self.seq_max, hi))
        self.dob_on += int(np.count_nonzero(s["flags"] & FLAG_DOB_ON))
        self.n += len(s)

    def _truth(self, t: StructArray) -> None:
        if len(t) == 0:
            return
        keys = t["period_index"].astype(np.int64)
        if self.truth_consecutive:
            start = int(keys[0]) if self.truth_n == 0 else self.truth_last + 1
            if (
                int(keys[0]) != start
                or int(keys[-1]) - start != len(keys) - 1
                or not np.all(np.diff(keys) == 1)
            ):
                self.truth_consecutive = False
                if self.truth_n:
                    self.truth_keys.append(np.arange(self.truth_first, self.truth_last + 1, dtype=np.int64))
            elif self.truth_n == 0:
                self.truth_first = start
        if not self.truth_consecutive:
            self.truth_keys.append(keys)
        self.truth_last = int(keys[-1])
        self.truth_n += len(keys)

    def _frames(self, f: StructArray) -> None:
        if len(f) == 0:
            return
        self.n_frames += len(f)
        tx = f["direction"] == CAN_TX
        if tx.any():
            self.n_tx += int(np.count_nonzero(tx))
            self.tx_ids = np.union1d(self.tx_ids, f["arbitration_id"][tx].astype(np.int64))
            stamps = np.concatenate([self.tx_smallest, f["timestamp_ns"][tx].astype(np.int64)])
            if len(stamps) > HEAD_TX_FRAMES:
                stamps = np.partition(stamps, HEAD_TX_FRAMES - 1)[:HEAD_TX_FRAMES]
            self.tx_smallest = np.sort(stamps)

    def truth_index(self) -> _Index | _Consecutive:
        if self.truth_consecutive:
            return _Consecutive(self.truth_first, self.truth_n)
        return _Index(np.concatenate(self.truth_keys))

    def summary(self) -> SampleSummary:
        return SampleSummary(self.n, int(self.spacing.median()) if self.spacing.n else None, self.dob_on)


class _Consecutive:
    """:class:`truth_match._Index` of consecutive period indexes, without holding them."""

    def __init__(self, first: int, n: int) -> None:
        self.first, self.n = first, n

    @property
    def lo(self) -> int:
        return self.first

    @property
    def hi(self) -> int:
        return self.first + self.n - 1

    def rows(self, wanted: IntArray) -> IntArray:
        rel = wanted - self.first
        return np.where((rel >= 0) & (rel < self.n), rel, -1)


def survey(path: Path, from_s: float) -> tuple[LoadedLog, Survey]:
    """Pass 1: the interpreted log (its arrays empty) and the survey."""
    with open_stream(path, SURVEY_FIELDS) as stream:
        sv = Survey(from_s)
        n_indexed = stream.counts.get(TOPIC_SAMPLE, 0)
        sv.picks = _Picks(_spread(n_indexed, BUS_PICKS), CLOCKS)
        for blocks in stream.blocks():
            sv.add(blocks)
        data = stream.header()
        data.complete = stream.complete
    data.events = sv.events
    if sv.n != n_indexed:  # messages lost to damage: pick again, from the samples read
        sv.picks = _Picks(_spread(sv.n, BUS_PICKS), CLOCKS)
        with open_stream(path, {TOPIC_SAMPLE: CLOCKS}, events=False) as again:
            g0 = 0
            for blocks in again.blocks():
                sv.picks.take(blocks.samples, g0)
                g0 += len(blocks.samples)
    return interpret(path, data, sv.summary()), sv


# ---------------------------------------------------------------------------------- bus load
class _BusWindow:
    """The counted frames of the window, with the frames near its ends held until the end."""

    def __init__(
        self, start_est: int | None, end_est: int, margin: int, tx_ids: IntArray, any_tx: bool
    ) -> None:
        self.start_est = start_est  # None: the window starts at the first sample (every frame)
        self.end_est = end_est
        self.margin = margin
        self.tx_ids = tx_ids
        self.any_tx = any_tx
        self.histogram = np.zeros(len(_WORST), dtype=np.int64)
        self.held_ts: list[IntArray] = []
        self.held_class: list[npt.NDArray[np.intp]] = []
        self.fd_in = 0
        self.fd_held: list[IntArray] = []

    def _held(self, ts: IntArray) -> npt.NDArray[np.bool_]:
        near = (np.abs(ts - self.end_est) <= self.margin) | (ts == 0)
        if self.start_est is not None:
            near |= np.abs(ts - self.start_est) <= self.margin
        return np.asarray(near, dtype=np.bool_)

    def _inside(self, ts: IntArray) -> npt.NDArray[np.bool_]:
        inside = ts <= self.end_est - self.margin
        if self.start_est is not None:
            inside &= ts > self.start_est + self.margin
        return np.asarray(inside, dtype=np.bool_)

    def add(self, frames: StructArray, fd_frames: StructArray) -> None:
        if len(frames):
            keep = (frames["flags"] & CAN_FLAG_ERROR) == 0
            if self.any_tx:
                tx = frames["direction"] == CAN_TX
                keep &= tx | ~np.isin(frames["arbitration_id"], self.tx_ids)
            ts = _i64(frames["timestamp_ns"])
            classes = frame_classes(frames)
            held = self._held(ts)
            self.histogram += np.bincount(classes[keep & ~held & self._inside(ts)], minlength=len(_WORST))
            self.held_ts.append(ts[keep & held])
            self.held_class.append(classes[keep & held])
        if len(fd_frames):
            fts = _i64(fd_frames["timestamp_ns"])
            held = self._held(fts)
            # the fd window includes its start (bus_usage): strictly inside is the same test
            self.fd_in += int(np.count_nonzero(~held & self._inside(fts)))
            self.fd_held.append(fts[held])

    def finish(self, start: int | None, end: int) -> tuple[npt.NDArray[np.int64], int]:
        """(class histogram, FD frames) for the final window bounds (``start`` None: from 0)."""
        histogram = self.histogram.copy()
        if self.held_ts:
            ts = np.concatenate(self.held_ts)
            classes = np.concatenate(self.held_class)
            inside = ts <= end
            if start is not None:
                inside &= ts > start
            histogram += np.bincount(classes[inside], minlength=len(_WORST))
        fd = self.fd_in
        if self.fd_held:
            fts = np.concatenate(self.fd_held)
            fd += int(np.count_nonzero((fts >= (start or 0)) & (fts <= end)))
        return histogram, fd


class _Nearest:
    """For each pick: the largest transmitted stamp below it and the smallest at or above it."""

    def __init__(self, picks: IntArray) -> None:
        self.picks = picks
        self.before = np.full(len(picks), np.iinfo(np.int64).min, dtype=np.int64)
        self.after = np.full(len(picks), np.iinfo(np.int64).max, dtype=np.int64)
        self.has_before = np.zeros(len(picks), dtype=bool)
        self.has_after = np.zeros(len(picks), dtype=bool)

    def add(self, tx_stamps: IntArray) -> None:
        if len(tx_stamps) == 0 or len(self.picks) == 0:
            return
        stamps = np.sort(tx_stamps)
        pos = np.searchsorted(stamps, self.picks, side="left")
        b = pos > 0
        cand = stamps[np.maximum(pos - 1, 0)]
        self.before = np.where(b, np.maximum(self.before, cand), self.before)
        self.has_before |= b
        a = pos < len(stamps)
        cand = stamps[np.minimum(pos, len(stamps) - 1)]
        self.after = np.where(a, np.minimum(self.after, cand), self.after)
        self.has_after |= a

    def nearest(self) -> IntArray:
        closer_after = np.abs(self.after - self.picks) < np.abs(self.before - self.picks)
        both = np.where(closer_after, self.after, self.before)
        return np.where(
            self.has_before & self.has_after, both, np.where(self.has_after, self.after, self.before)
        )


@dataclass
class _BusPlan:
    clock: str
    offset0: int
    window: _BusWindow
    nearest: _Nearest


def _bus_plan(log: LoadedLog, sv: Survey) -> _BusPlan | None:
    """The clock and first offset of :func:`bus_usage.clock_offset_ns`, from the survey."""
    n_periods = sv.n - (sv.first if sv.first is not None else sv.n)
    if n_periods <= 0 or sv.n_frames == 0 or not log.bitrate_bps or sv.n_tx == 0 or sv.picks is None:
        return None
    best: tuple[float, str, int] | None = None
    for name in CLOCKS:
        clock = np.concatenate(sv.head[name])
        if clock[0] <= 0 and name == "tx_time_ns":
            continue
        spread, offset = _offset_against(clock, sv.tx_smallest)
        if best is None or spread < best[0]:
            best = (spread, name, offset)
    if best is None:
        return None
    _, name, offset = best
    first = sv.first if sv.first is not None else sv.n
    start = sv.before_first[name] + offset if first > 0 else None
    window = _BusWindow(start, sv.last[name] + offset, MARGIN_NS, sv.tx_ids, sv.n_tx > 0)
    return _BusPlan(name, offset, window, _Nearest(sv.picks.values[name] + offset))


def _bus_result(log: LoadedLog, sv: Survey, plan: _BusPlan, path: Path) -> dict[str, Any]:
    offset = plan.offset0 + int(np.median(plan.nearest.nearest() - plan.nearest.picks))
    first = sv.first if sv.first is not None else sv.n
    start = max(sv.before_first[plan.clock] + offset, 0) if first > 0 else None
    end = max(sv.last[plan.clock] + offset, 0)
    window = plan.window
    if abs(offset - plan.offset0) > window.margin:  # count the frames again with the final bounds
        window = _BusWindow(start, end, 0, sv.tx_ids, sv.n_tx > 0)
        with open_stream(path, {TOPIC_CAN: METRICS_FIELDS[TOPIC_CAN], TOPIC_CAN_FD: ("timestamp_ns",)},
                         events=False) as stream:  # fmt: skip
            for b in stream.blocks():
                window.add(b.frames, b.fd_frames)
    histogram, fd_in = window.finish(start, end)
    bitrate = log.bitrate_bps
    assert bitrate
    return load_figures(histogram, sv.n - first, log.period_ns, bitrate, fd_in)


# ---------------------------------------------------------------------------------- truth join
class _TruthJoin:
    """Truth rows (global numbers) buffered from the stream until the samples want them."""

    def __init__(self, index: _Index | _Consecutive, offset: int | None) -> None:
        self.index = index
        self.offset = offset  # None: no sample matches
        self.start = 0  # global row of the buffer's first row
        self.states: list[FloatArray] = []
        self.dist: list[FloatArray] = []
        self.held = 0
        self.ended = False
        self.lost = 0  # samples whose row had already left the buffer (truth out of order)

    @property
    def end(self) -> int:
        return self.start + self.held

    def add(self, truth: StructArray) -> None:
        if len(truth):
            self.states.append(np.asarray(truth["state"], dtype=np.float64).reshape(len(truth), -1))
            self.dist.append(np.asarray(truth["disturbance_a"], dtype=np.float64).reshape(len(truth), -1))
            self.held += len(truth)

    def rows(self, seq: IntArray) -> IntArray:
        if self.offset is None:
            return np.full(len(seq), -1, dtype=np.int64)
        return self.index.rows(seq + self.offset)

    def ready(self, rows: IntArray) -> bool:
        wanted = rows[rows >= 0]
        return self.ended or len(wanted) == 0 or int(wanted.max()) < self.end

    def take(self, rows: IntArray, width_x: int, width_w: int) -> tuple[FloatArray, FloatArray, IntArray]:
        """(states, disturbances) of ``rows`` (NaN rows where -1) and the rows actually found."""
        if len(self.states) > 1:
            self.states = [np.concatenate(self.states)]
            self.dist = [np.concatenate(self.dist)]
        states = self.states[0] if self.states else np.zeros((0, width_x))
        dist = self.dist[0] if self.dist else np.zeros((0, width_w))
        local = rows - self.start
        found = (rows >= 0) & (local >= 0) & (local < self.held)
        self.lost += int(np.count_nonzero((rows >= 0) & ~found))
        at = np.where(found, local, 0)
        x = states[at] if len(states) else np.zeros((len(rows), width_x))
        w = dist[at] if len(dist) else np.zeros((len(rows), width_w))
        x[~found] = np.nan
        w[~found] = np.nan
        wanted = rows[found]
        if len(wanted):  # rows below what this block wanted are not wanted again (seq ascends)
            self._drop(int(wanted.min()) - self.start)
        return x, w, np.where(found, rows, -1)

    def _drop(self, count: int) -> None:
        if count <= 0 or not self.states:
            return
        self.states = [self.states[0][count:]]
        self.dist = [self.dist[0][count:]]
        self.start += count
        self.held -= count


# ---------------------------------------------------------------------------------- accumulators
class _Columns:
    """Sum of squares and count of the finite values, and the maximum |value|, per column."""

    def __init__(self) -> None:
        self.sums: list[float] = []
        self.counts: list[int] = []
        self.maxima: list[float] = []
        self.finite_maxima: list[float | None] = []  # of the finite values only
        self.rows = 0

    def add(self, columns: list[FloatArray]) -> None:
        if not self.sums:
            self.sums = [0.0] * len(columns)
            self.counts = [0] * len(columns)
            self.maxima = [-np.inf] * len(columns)
            self.finite_maxima = [None] * len(columns)
        for j, c in enumerate(columns):
            finite = c[np.isfinite(c)]
            self.sums[j] += float(np.dot(finite, finite))
            self.counts[j] += len(finite)
            if len(finite):
                fm = float(np.abs(finite).max())
                old = self.finite_maxima[j]
                self.finite_maxima[j] = fm if old is None else max(old, fm)
            if len(c):
                m = float(np.abs(c).max())
                self.maxima[j] = m if (np.isnan(m) or np.isnan(self.maxima[j])) else max(self.maxima[j], m)
        self.rows += len(columns[0]) if columns else 0

    def total(self) -> tuple[float, int]:
        total, count = 0.0, 0
        for s, c in zip(self.sums, self.counts, strict=True):
            total += s
            count += c
        return total, count

    def rms(self) -> float | None:
        total, count = self.total()
        return math.sqrt(total / count) if count else None

    def max(self) -> float | None:
        return max(self.maxima) if self.rows else None

    def rms_per_column(self, width: int) -> list[float | None]:
        if not self.sums:
            return [None] * width
        return [math.sqrt(s / c) if c else None for s, c in zip(self.sums, self.counts, strict=True)]

    def max_per_column(self, width: int) -> list[float | None]:
        return list(self.finite_maxima) if self.sums else [None] * width


@dataclass
class _Accumulators:
    period_ns: int
    covered: Callable[[IntArray], IntArray] | None
    n_plant_for_estimation: int  # 0: the log's layout gives no estimation error
    n: int = 0
    t_first: float | None = None
    t_last: float | None = None
    track_truth: _Columns = field(default_factory=_Columns)
    track_measured: _Columns = field(default_factory=_Columns)
    dist: _Columns = field(default_factory=_Columns)
    dist_error: _Columns = field(default_factory=_Columns)
    wu: list[float] = field(default_factory=list)
    gain_ww: list[float] = field(default_factory=list)  # per input, over the finite pairs
    gain_wu: list[float] = field(default_factory=list)
    currents: _Columns = field(default_factory=_Columns)
    estimation: list[_Columns] = field(default_factory=list)
    saturated: int = 0
    overruns: int = 0
    feedback_missing: int = 0
    truth_samples: int = 0
    absent: int = 0
    skipped: int = 0
    out_of_sequence: int = 0
    non_finite: int = 0
    latency: IntCounts = field(default_factory=IntCounts)
    jitter: IntCounts = field(default_factory=IntCounts)
    compute: IntCounts = field(default_factory=IntCounts)
    last: tuple[int, bool, int] | None = None  # (rx, has feedback, seq) of the previous window sample

    def add(
        self, s: StructArray, t_s: FloatArray, y_ref: FloatArray, y_true: FloatArray, x_true: FloatArray,
        w_A: FloatArray, has_fb: npt.NDArray[np.bool_], has_truth: npt.NDArray[np.bool_],
    ) -> None:  # fmt: skip
        if len(s) == 0:
            return
        if self.t_first is None:
            self.t_first = float(t_s[0])
        self.t_last = float(t_s[-1])
        self.n += len(s)
        self.non_finite += non_finite_rows(s)
        p = y_ref.shape[1]
        y_meas = np.asarray(s["position"], dtype=np.float64).reshape(len(s), -1)
        self.track_truth.add([y_ref[has_truth, j] - y_true[has_truth, j] for j in range(p)])
        self.track_measured.add([y_ref[has_fb, j] - y_meas[has_fb, j] for j in range(p)])
        m = w_A.shape[1]
        dist = [w_A[has_truth, j] for j in range(m)]
        u_dist = np.asarray(s["u_dist"], dtype=np.float64).reshape(len(s), -1)
        u = [u_dist[has_truth, j] for j in range(m)]
        self.dist.add(dist)
        self.dist_error.add([d + v for d, v in zip(dist, u, strict=True)])
        wu = [-float(np.dot(d, v)) for d, v in zip(dist, u, strict=True)]
        self.wu = wu if not self.wu else [a + b for a, b in zip(self.wu, wu, strict=True)]
        oks = [np.isfinite(d) & np.isfinite(v) for d, v in zip(dist, u, strict=True)]
        ww = [float(np.dot(d[ok], d[ok])) for d, ok in zip(dist, oks, strict=True)]
        du = [float(np.dot(d[ok], v[ok])) for d, v, ok in zip(dist, u, oks, strict=True)]
        self.gain_ww = ww if not self.gain_ww else [a + b for a, b in zip(self.gain_ww, ww, strict=True)]
        self.gain_wu = du if not self.gain_wu else [a + b for a, b in zip(self.gain_wu, du, strict=True)]
        applied = np.asarray(s["u_applied_a"], dtype=np.float64).reshape(len(s), -1)
        self.currents.add([applied[:, j] for j in range(m)])
        if self.n_plant_for_estimation:
            x_hat = np.asarray(s["x_hat"], dtype=np.float64).reshape(len(s), -1)
            if not self.estimation:
                self.estimation = [_Columns() for _ in range(self.n_plant_for_estimation)]
            for j, acc in enumerate(self.estimation):
                acc.add([x_true[has_truth, j] - x_hat[has_truth, j]])
        flags = s["flags"]
        self.saturated += int(np.count_nonzero(flags & FLAG_SATURATED))
        self.overruns += int(np.count_nonzero(flags & FLAG_OVERRUN))
        self.feedback_missing += int(np.count_nonzero(~has_fb))
        self.truth_samples += int(np.count_nonzero(has_truth))
        self._gaps_and_timing(s, has_fb)

    def _gaps_and_timing(self, s: StructArray, fb: npt.NDArray[np.bool_]) -> None:
        seq = s["seq"].astype(np.int64)
        rx = s["rx_time_ns"].view(np.int64)
        tx = s["tx_time_ns"].view(np.int64)
        self.latency.add((tx - rx)[fb & (tx >= rx)])
        self.compute.add(s["compute_ns"])
        if self.last is not None:
            rx_c = np.concatenate([[self.last[0]], rx])
            fb_c = np.concatenate([[self.last[1]], fb])
            seq_c = np.concatenate([[self.last[2]], seq])
        else:
            rx_c, fb_c, seq_c = rx, fb, seq
        steps = np.diff(seq_c)
        self.out_of_sequence += out_of_sequence(steps)
        pair = fb_c[1:] & fb_c[:-1] & (steps == 1)
        self.jitter.add(np.abs(np.diff(rx_c) - self.period_ns)[pair])
        at = np.flatnonzero(steps > 1)
        if len(at):
            lo, hi = seq_c[at] + 1, seq_c[at + 1]
            self.absent += int(np.sum(hi - lo))
            if self.covered is not None:
                self.skipped += int(np.sum(self.covered(hi) - self.covered(lo)))
        self.last = (int(rx[-1]), bool(fb[-1]), int(seq[-1]))

    def tracking(self) -> tuple[float | None, float | None, str, int]:
        truth = self.truth_samples > 0
        acc, source = (self.track_truth, "truth") if truth else (self.track_measured, "measured")
        if acc.rows == 0:
            return None, None, source, 0
        return acc.rms(), acc.max(), source, acc.rows

    def disturbance(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "disturbance_rms": None,
            "disturbance_estimate_error_rms": None,
            "disturbance_estimate_gain": None,
            "estimation_error_rms": None,
        }
        if self.truth_samples == 0:
            return out
        out["disturbance_rms"] = self.dist.rms()
        out["disturbance_estimate_error_rms"] = self.dist_error.rms()
        ww = self.dist.total()[0]
        wu = 0.0
        for x in self.wu:
            wu += x
        out["disturbance_estimate_gain"] = wu / ww if ww > 0 else None
        if self.n_plant_for_estimation:
            out["estimation_error_rms"] = [acc.rms() for acc in self.estimation]
        return out

    def per_axis(self, p: int, m: int) -> dict[str, Any]:
        """:func:`dob_hil.analysis.metrics._per_axis` from the accumulated sums."""
        track = self.track_truth if self.truth_samples > 0 else self.track_measured
        out: dict[str, Any] = {
            "tracking_error_rms_per_output": track.rms_per_column(p),
            "tracking_error_max_per_output": track.max_per_column(p),
            "disturbance_rms_per_input": [None] * m,
            "disturbance_estimate_error_rms_per_input": [None] * m,
            "disturbance_estimate_gain_per_input": [None] * m,
        }
        if self.truth_samples:
            out["disturbance_rms_per_input"] = self.dist.rms_per_column(m)
            out["disturbance_estimate_error_rms_per_input"] = self.dist_error.rms_per_column(m)
            out["disturbance_estimate_gain_per_input"] = [
                0.0 - du / ww if ww > 0 else None for ww, du in zip(self.gain_ww, self.gain_wu, strict=True)
            ]
        out["current_rms_A_per_input"] = self.currents.rms_per_column(m)
        out["current_max_A_per_input"] = self.currents.max_per_column(m)
        return out

    def timing(self) -> dict[str, Any]:
        return {
            "latency_us": self.latency.distribution(1e-3),
            "period_jitter_us": self.jitter.distribution(1e-3),
            "compute_us": self.compute.distribution(1e-3),
        }

    def percentile_method(self) -> str:
        coarse = [d.method for d in (self.latency, self.jitter, self.compute) if d.coarse]
        return coarse[0] if coarse else self.latency.method


# ---------------------------------------------------------------------------------- metrics pass
@dataclass
class _PassResult:
    acc: _Accumulators
    pick_y: FloatArray  # measured output of the truth-match picks
    pick_true: FloatArray  # true output at the matched rows (NaN where none)
    pick_seq: IntArray
    lost: int


def _ranks_of_valid(n_valid: int) -> IntArray:
    return _spread(n_valid, SCORE_SAMPLES)


def _covered(events: list[dict[str, Any]]) -> Callable[[IntArray], IntArray] | None:
    ranges = skipped_ranges(events)
    return _covered_below(ranges) if ranges else None


def _metrics_pass(log: LoadedLog, sv: Survey, offset: int | None, bus: _BusPlan | None) -> _PassResult:
    layout = log.data.layout
    p = layout.n_outputs
    design = log.design
    C = design.C if design is not None else np.eye(p, layout.n_states)
    C_cont = design.C_cont if design is not None else np.eye(p, layout.n_plant_states)
    n_est = layout.n_plant_states if layout.n_plant_states <= layout.n_states else 0
    acc = _Accumulators(log.period_ns, _covered(sv.events), n_est)
    join = _TruthJoin(sv.truth_index(), offset)
    first = sv.first if sv.first is not None else sv.n
    ranks = _ranks_of_valid(sv.n_valid)
    pick_y = np.full((len(ranks), p), np.nan)
    pick_true = np.full((len(ranks), p), np.nan)
    pick_seq = np.zeros(len(ranks), dtype=np.int64)
    pending: deque[tuple[StructArray, int, IntArray]] = deque()
    counters = {"g0": 0, "valid": 0}

    def process(s: StructArray, g0: int, rows: IntArray) -> None:
        x_true, w_A, rows = join.take(rows, layout.n_plant_states, layout.n_inputs)
        has_truth = rows >= 0
        has_fb = (s["flags"] & FLAG_FEEDBACK_MISSING) == 0
        y_true = x_true @ C_cont.T
        # truth-match picks: the valid samples of ranks r (counted over the whole log)
        v0 = counters["valid"]
        valid_idx = np.flatnonzero(has_fb)
        lo, hi = np.searchsorted(ranks, [v0, v0 + len(valid_idx)])
        if hi > lo:
            at = valid_idx[ranks[lo:hi] - v0]
            pick_y[lo:hi] = np.asarray(s["position"], dtype=np.float64).reshape(len(s), -1)[at]
            pick_true[lo:hi] = y_true[at]
            pick_seq[lo:hi] = s["seq"][at].astype(np.int64)
        counters["valid"] = v0 + len(valid_idx)
        j = max(first - g0, 0)
        if j >= len(s):
            return
        w = slice(j, None)
        t_s = np.asarray((s["time_ns"][w].view(np.int64) - sv.t0) * 1e-9, dtype=np.float64)
        with np.errstate(invalid="ignore", over="ignore"):  # non-finite rows: counted, left out
            y_ref = np.asarray(s["x_ref"][w], dtype=np.float64).reshape(len(s) - j, -1) @ C.T
        acc.add(s[w], t_s, y_ref, y_true[w], x_true[w], w_A[w], has_fb[w], has_truth[w])

    with open_stream(log.path, METRICS_FIELDS, events=False) as stream:
        for b in stream.blocks():
            join.add(b.truth)
            if bus is not None:
                bus.window.add(b.frames, b.fd_frames)
                tx = b.frames["direction"] == CAN_TX
                bus.nearest.add(b.frames["timestamp_ns"][tx].astype(np.int64))
            if len(b.samples):
                rows = join.rows(b.samples["seq"].astype(np.int64))
                pending.append((b.samples, counters["g0"], rows))
                counters["g0"] += len(b.samples)
            # truth rows that do not arrive within MAX_PENDING groups count as missing
            while pending and (join.ready(pending[0][2]) or len(pending) > MAX_PENDING):
                process(*pending.popleft())
        join.ended = True
        while pending:
            process(*pending.popleft())
    return _PassResult(acc, pick_y, pick_true, pick_seq, join.lost)


# ---------------------------------------------------------------------------------- truth offset
def _score(y_true: FloatArray, y_pick: FloatArray) -> float:
    return float(np.median(np.abs(y_true - y_pick).max(axis=1)))


def _lockstep_fits(log: LoadedLog, sv: Survey, res: _PassResult) -> bool:
    """match_truth's first test: offset 0 agrees within an encoder count on the picks."""
    if sv.n == 0 or sv.truth_n == 0 or sv.n_valid == 0:
        return True  # match_truth keeps offset 0 (or finds no truth at all)
    if np.isnan(res.pick_true).any():
        return False
    return _score(res.pick_true, res.pick_y) <= encoder_quantum(log)


def _candidate_diffs(
    path: Path, index: _Consecutive, candidates: IntArray, pick_seq: IntArray, pick_y: FloatArray,
    C_cont: FloatArray,
) -> tuple[FloatArray, IntArray]:  # fmt: skip
    """match_truth's (candidates x picks) matrix of max |true - measured output| (inf where the
    truth has no row), filled as the truth records stream by: memory is the matrix (8 B per
    candidate and pick), not the rows it is made from."""
    diff = np.full((len(candidates), len(pick_seq)), np.inf)
    present = np.zeros(len(candidates), dtype=np.int64)
    for s_i in pick_seq.tolist():
        rel = s_i + candidates - index.first
        present += (rel >= 0) & (rel < index.n)
    with open_stream(path, {TOPIC_TRUTH: ("state",)}, events=False) as stream:
        g0 = 0
        for b in stream.blocks():
            t = b.truth
            if len(t) == 0:
                continue
            states = np.asarray(t["state"], dtype=np.float64).reshape(len(t), -1)
            for i, s_i in enumerate(pick_seq.tolist()):
                # candidate c wants the truth row s_i + c - first: those in this block
                lo = g0 + index.first - s_i
                a, z = np.searchsorted(candidates, [lo, lo + len(t)])
                if z > a:
                    y_true = states[candidates[a:z] - lo] @ C_cont.T
                    diff[a:z, i] = np.abs(y_true - pick_y[i][None, :]).max(axis=1)
            g0 += len(t)
    return diff, present


def _candidate_diffs_held(
    path: Path, index: _Index, candidates: IntArray, pick_seq: IntArray, pick_y: FloatArray,
    C_cont: FloatArray,
) -> tuple[FloatArray, IntArray]:  # fmt: skip
    """As :func:`_candidate_diffs` for truth records whose period indexes are not consecutive
    (the index is held; the rows of every candidate are gathered at once, as match_truth does)."""
    rows = index.rows(pick_seq[None, :] + candidates[:, None])
    wanted = np.unique(rows[rows >= 0])
    p = C_cont.shape[0]
    outputs = np.zeros((len(wanted), p))
    with open_stream(path, {TOPIC_TRUTH: ("state",)}, events=False) as stream:
        g0 = 0
        for b in stream.blocks():
            t = b.truth
            a, z = np.searchsorted(wanted, [g0, g0 + len(t)])
            if z > a:
                states = np.asarray(t["state"], dtype=np.float64).reshape(len(t), -1)
                outputs[a:z] = states[wanted[a:z] - g0] @ C_cont.T
            g0 += len(t)
    y_true = (
        outputs[np.searchsorted(wanted, np.maximum(rows, 0))] if len(wanted) else np.zeros((*rows.shape, p))
    )
    y_true = y_true.reshape(*rows.shape, p)
    diff = np.abs(y_true - pick_y[None, :, :]).max(axis=2)
    return np.where(rows >= 0, diff, np.inf), (rows >= 0).sum(axis=1)


def _search_offset(log: LoadedLog, sv: Survey, res: _PassResult) -> int | None:
    """match_truth's candidate search, with the truth outputs fetched in one pass."""
    index = sv.truth_index()
    quantum = encoder_quantum(log)
    d0 = int(np.argmax(sv.fb_offsets))
    lo = index.lo - sv.seq_max
    hi = index.hi - sv.seq_min
    start = d0 + 256 * ((lo - d0) // 256)
    candidates = np.unique(np.concatenate([[0], np.arange(start, hi + 1, 256, dtype=np.int64)]))
    p = log.data.layout.n_outputs
    design = log.design
    C_cont = design.C_cont if design is not None else np.eye(p, log.data.layout.n_plant_states)
    if isinstance(index, _Consecutive):
        diff, present = _candidate_diffs(log.path, index, candidates, res.pick_seq, res.pick_y, C_cont)
    else:
        diff, present = _candidate_diffs_held(log.path, index, candidates, res.pick_seq, res.pick_y, C_cont)
    medians = np.concatenate([np.median(diff[i : i + 4096], axis=1) for i in range(0, len(diff), 4096)])
    scores = np.where(2 * present >= len(res.pick_y), medians, np.inf)  # by rows: no copy of diff
    best = int(np.argmin(scores))
    zero = int(np.flatnonzero(candidates == 0)[0])
    if np.isfinite(scores[zero]) and scores[zero] <= scores[best] + 2.0 * quantum:
        best = zero
    if not np.isfinite(scores[best]):
        return None
    return int(candidates[best])


# ---------------------------------------------------------------------------------- entry points
def streamed_metrics(log: LoadedLog, sv: Survey) -> dict[str, Any]:
    """The metrics of ``log`` (interpreted by :func:`survey`) over the survey's window."""
    bus = _bus_plan(log, sv)
    res = _metrics_pass(log, sv, 0, bus)
    if not _lockstep_fits(log, sv, res):
        offset = _search_offset(log, sv, res)
        bus = _bus_plan(log, sv)
        res = _metrics_pass(log, sv, offset, bus)
    acc = res.acc
    layout = log.data.layout
    extra: dict[str, Any] = {
        **acc.per_axis(layout.n_outputs, layout.n_inputs),
        "timing_percentiles": acc.percentile_method(),
    }
    if res.lost:
        log.warnings.append(f"{res.lost} samples not matched to ground truth: truth records out of order")
    figures = WindowFigures(
        samples=acc.n,
        t_first_s=acc.t_first,
        t_last_s=acc.t_last,
        log_end_s=(sv.last["time_ns"] - sv.t0) * 1e-9 if sv.n else 0.0,
        tracking=acc.tracking(),
        disturbance=acc.disturbance(),
        saturated=acc.saturated,
        overruns=acc.overruns,
        feedback_missing=acc.feedback_missing,
        skipped=acc.skipped,
        dropped=acc.absent - acc.skipped,
        timing=acc.timing(),
        bus=_bus_result(log, sv, bus, log.path) if bus is not None else None,
        truth_samples=acc.truth_samples,
        extra=extra,
        out_of_sequence=acc.out_of_sequence,
        time_back=sv.time_back,
        non_finite=acc.non_finite,
        log_samples=sv.n,
    )
    return assemble_metrics(log, sv.from_s, figures)


def analyze_streamed(path: Path | str, from_s: float) -> tuple[LoadedLog, dict[str, Any]]:
    """Survey and metrics of one log, streamed (module docstring)."""
    return_large_buffers_to_the_os()
    log, sv = survey(Path(path), from_s)
    return log, streamed_metrics(log, sv)


def x_ref_blocks(path: Path) -> Iterator[FloatArray]:
    """The samples' ``x_ref`` block by block (for comparing the references of long logs)."""
    from dob_hil.log.reader import iter_channel

    for block in iter_channel(path, TOPIC_SAMPLE, ["x_ref"]):
        yield np.asarray(block["x_ref"])


__all__ = ["METRICS_FIELDS", "SURVEY_FIELDS", "Survey", "analyze_streamed", "streamed_metrics", "survey"]
