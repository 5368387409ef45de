"""Metrics of one run over a window (``from_s`` seconds after the first sample to the end).

Vectorised over the log's arrays. The result is a JSON-ready dictionary (floats, ints, lists,
None for what the log cannot tell); its keys:

``file``, ``scenario``, ``mode``, ``dob_enabled``, ``complete`` (closed cleanly, nothing lost: no
dropped or out-of-sequence sample in the window either),
``window_start_s``, ``samples`` (in the window), ``duration_s`` (time the window spans),
``tracking_error_rms`` / ``tracking_error_max``: reference output ``C x_ref`` minus the true plant
output at the sample instants with ground truth (``tracking_error_source`` "truth"), or minus the
measured output where the log holds no truth ("measured"), over all outputs;
``disturbance_rms``: the injected disturbance w; ``disturbance_estimate_error_rms``: w + u_dist
(u_dist compensates w, so -u_dist is the estimate); ``disturbance_estimate_gain``: least-squares
gain of the estimate on w (1 = full amplitude; None without truth or with w = 0);
``estimation_error_rms``: true minus estimated (x_hat) plant state, one entry per plant state;
``saturated_fraction``; ``overruns`` (flag bit 1); ``feedback_missing`` (bit 2, substituted);
``skipped_samples`` (sequence gaps the runner explained in ``feedback_lost``/``overrun_skip``
events); ``dropped_samples`` (sequence gaps nobody explained: lost from the log);
``non_finite_samples`` (samples of the window with NaN or inf in a field the figures use: left
out of those figures, with a warning); ``out_of_sequence_samples`` (samples whose sequence
number does not exceed the one before: duplicated or reordered records; any makes the log
incomplete, with a warning);
``log_dropped_records`` (the summary's count of records of any kind the writer dropped, whole run);
``latency_us`` (command send minus feedback receive), ``period_jitter_us``
(|receive interval - period| between consecutive samples with feedback) and ``compute_us``
(controller step): each ``{"p50", "p99", "max", "n"}``; ``timing_percentiles``: how those
percentiles were computed ("exact": numpy's linear percentile of every value; a streamed log with
more than a million distinct nanosecond values says which rounding it used, see
:mod:`dob_hil.analysis.int_distribution`); ``bus_load`` (:mod:`bus_usage`);
``truth_samples`` (samples matched to ground truth); ``notes`` and ``warnings`` (lists of text).

Per axis (lists, one entry per plant output or input, in order; the combined keys above stay):
``tracking_error_rms_per_output`` / ``tracking_error_max_per_output`` (the same samples and source
as the combined tracking error); ``disturbance_rms_per_input``,
``disturbance_estimate_error_rms_per_input`` and ``disturbance_estimate_gain_per_input`` (None
entries without truth); ``current_rms_A_per_input`` / ``current_max_A_per_input`` (|applied
current|, every sample of the window).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from dob_hil.analysis.bus_usage import bus_load
from dob_hil.analysis.loaded import LoadedLog
from dob_hil.analysis.rerun import skipped_ranges
from dob_hil.analysis.signals import Signals, derive_signals
from dob_hil.log.schemas import FLAG_OVERRUN, FLAG_SATURATED

FloatArray = npt.NDArray[np.float64]


def distribution(values: npt.NDArray[Any], scale: float = 1.0) -> dict[str, float | int] | None:
    """p50, p99, max (times ``scale``) and the count, or None for no values."""
    if len(values) == 0:
        return None
    v = np.asarray(values, dtype=np.float64) * scale
    p50, p99 = np.percentile(v, [50.0, 99.0])
    return {"p50": float(p50), "p99": float(p99), "max": float(v.max()), "n": len(v)}


def window_start(t_s: FloatArray, from_s: float) -> int:
    """Index of the first sample at or after ``from_s``; len(t_s) if none. A damaged log's times
    may not ascend: no binary search (it would land anywhere)."""
    return first_at_or_after(t_s, from_s)


def first_at_or_after(t_s: npt.NDArray[np.floating[Any]], from_s: float) -> int:
    """Index of the first ``t_s`` at or after ``from_s`` (in array order); len(t_s) if none."""
    at = np.flatnonzero(t_s >= from_s - 1e-12)
    return int(at[0]) if len(at) else len(t_s)


# the sample fields the figures are computed from: a row with a non-finite value in any of them is
# left out of the figures that use it, and counted (``non_finite_samples``, a warning)
FINITE_FIELDS: Final = ("position", "x_ref", "x_hat", "u_dist", "u_applied_a")


def non_finite_rows(s: npt.NDArray[Any]) -> int:
    """How many samples hold a non-finite value in one of :data:`FINITE_FIELDS`."""
    if len(s) == 0:
        return 0
    bad = np.zeros(len(s), dtype=np.bool_)
    for name in FINITE_FIELDS:
        values = np.asarray(s[name], dtype=np.float64).reshape(len(s), -1)
        bad |= ~np.isfinite(values).all(axis=1)
    return int(np.count_nonzero(bad))


def time_steps_back(t_ns: npt.NDArray[np.int64]) -> int:
    """How many consecutive-sample time steps go back (a damaged log's clock)."""
    return int(np.count_nonzero(np.diff(t_ns) < 0))


def gap_accounting(seq: npt.NDArray[np.int64], events: list[dict[str, Any]]) -> tuple[int, int]:
    """(skipped, dropped): sequence numbers absent between the samples ``seq``, split into those
    a runner event (``feedback_lost``/``overrun_skip`` with ``first_sample`` and ``count``) says
    were skipped on purpose, and the rest (lost from the log)."""
    if len(seq) < 2:
        return 0, 0
    steps = np.diff(seq)
    at = np.flatnonzero(steps > 1)
    if len(at) == 0:
        return 0, 0
    lo = seq[at] + 1  # first absent seq of each gap
    hi = seq[at + 1]  # one past the last
    ranges = skipped_ranges(events)
    absent = int(np.sum(hi - lo))
    if not ranges:
        return 0, absent
    covered = _covered_below(ranges)
    skipped = int(np.sum(covered(hi) - covered(lo)))
    return skipped, absent - skipped


def _covered_below(ranges: list[tuple[int, int]]) -> Callable[[npt.NDArray[np.int64]], npt.NDArray[np.int64]]:
    """F(x): how many integers below x lie in the union of the half-open ``ranges`` (vectorised)."""
    merged: list[list[int]] = []
    for a, b in sorted(ranges):
        if merged and a <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    starts = np.array([m[0] for m in merged], dtype=np.int64)
    lengths = np.array([m[1] - m[0] for m in merged], dtype=np.int64)
    before = np.concatenate([[0], np.cumsum(lengths)[:-1]])

    def covered(x: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
        i = np.searchsorted(starts, x, side="right") - 1
        ic = np.maximum(i, 0)
        inside = np.clip(x - starts[ic], 0, lengths[ic])
        return np.where(i >= 0, before[ic] + inside, 0)

    return covered


def _columns(values: npt.NDArray[Any], w: slice, mask: npt.NDArray[np.bool_], width: int) -> list[FloatArray]:
    """The first ``width`` columns of values[w][mask] as 1-D arrays (ufuncs on one column of a
    structured field run a fast strided inner loop; on (n, 2) blocks they iterate per row).
    No boolean gather (a copy) when the mask is all true."""
    part = values[w]
    every = bool(mask.all())
    return [part[:, j] if every else part[:, j][mask] for j in range(width)]


def _sum_sq(columns: list[FloatArray]) -> tuple[float, int]:
    total, count = 0.0, 0
    for c in columns:
        finite = c[np.isfinite(c)]
        total += float(np.dot(finite, finite))
        count += len(finite)
    return total, count


def _rms_of(columns: list[FloatArray]) -> float | None:
    total, count = _sum_sq(columns)
    return math.sqrt(total / count) if count else None


def _tracking_errors(sig: Signals, w: slice) -> tuple[list[FloatArray], str]:
    """Reference minus output, one column per output: against the truth where there is any,
    else against the measurement (samples with feedback)."""
    truth = sig.has_truth[w]
    p = sig.y_ref.shape[1]
    if truth.any():
        mask, other, source = truth, sig.y_true, "truth"
    else:
        mask, other, source = sig.has_feedback[w], sig.y_meas, "measured"
    refs, outs = _columns(sig.y_ref, w, mask, p), _columns(other, w, mask, p)
    return [r - y for r, y in zip(refs, outs, strict=True)], source


def _tracking(sig: Signals, w: slice) -> tuple[float | None, float | None, str, int]:
    e, source = _tracking_errors(sig, w)
    used = len(e[0]) if e else 0
    if used == 0:
        return None, None, source, 0
    maxima = [m for m in (_max_abs(c) for c in e) if m is not None]  # non-finite left out, as by _rms_of
    return _rms_of(e), max(maxima) if maxima else None, source, used


def _disturbance(log: LoadedLog, sig: Signals, w: slice) -> dict[str, Any]:
    truth = sig.has_truth[w]
    out: dict[str, Any] = {
        "disturbance_rms": None,
        "disturbance_estimate_error_rms": None,
        "disturbance_estimate_gain": None,
        "estimation_error_rms": None,
    }
    if not truth.any():
        return out
    m = sig.w_A.shape[1]
    dist = _columns(sig.w_A, w, truth, m)
    u_dist = _columns(log.data.samples["u_dist"], w, truth, m)
    out["disturbance_rms"] = _rms_of(dist)
    out["disturbance_estimate_error_rms"] = _rms_of([d + u for d, u in zip(dist, u_dist, strict=True)])
    ww = _sum_sq(dist)[0]
    wu = sum(-float(np.dot(d, u)) for d, u in zip(dist, u_dist, strict=True))
    out["disturbance_estimate_gain"] = wu / ww if ww > 0 else None
    n_plant = log.data.layout.n_plant_states
    if n_plant <= log.data.layout.n_states:
        x_true = _columns(sig.x_true, w, truth, n_plant)
        x_hat = _columns(log.data.samples["x_hat"], w, truth, n_plant)
        out["estimation_error_rms"] = [_rms_of([t - h]) for t, h in zip(x_true, x_hat, strict=True)]
    return out


def _max_abs(column: FloatArray) -> float | None:
    finite = column[np.isfinite(column)]
    return float(np.abs(finite).max()) if len(finite) else None


def _per_axis(log: LoadedLog, sig: Signals, w: slice) -> dict[str, Any]:
    """The per-output and per-input metrics of the module docstring."""
    e, _ = _tracking_errors(sig, w)
    m = log.data.layout.n_inputs
    out: dict[str, Any] = {
        "tracking_error_rms_per_output": [_rms_of([c]) for c in e],
        "tracking_error_max_per_output": [_max_abs(c) for c in e],
        "disturbance_rms_per_input": [None] * m,
        "disturbance_estimate_error_rms_per_input": [None] * m,
        "disturbance_estimate_gain_per_input": [None] * m,
    }
    truth = sig.has_truth[w]
    if truth.any():
        dist = _columns(sig.w_A, w, truth, m)
        u_dist = _columns(log.data.samples["u_dist"], w, truth, m)
        out["disturbance_rms_per_input"] = [_rms_of([d]) for d in dist]
        out["disturbance_estimate_error_rms_per_input"] = [
            _rms_of([d + u]) for d, u in zip(dist, u_dist, strict=True)
        ]
        gains: list[float | None] = []
        for d, u in zip(dist, u_dist, strict=True):
            ok = np.isfinite(d) & np.isfinite(u)
            ww = float(np.dot(d[ok], d[ok]))
            gains.append(0.0 - float(np.dot(d[ok], u[ok])) / ww if ww > 0 else None)  # 0 - : no -0.0
        out["disturbance_estimate_gain_per_input"] = gains
    every = np.ones(len(sig.t_s[w]), dtype=np.bool_)
    currents = _columns(log.data.samples["u_applied_a"], w, every, m)
    out["current_rms_A_per_input"] = [_rms_of([c]) for c in currents]
    out["current_max_A_per_input"] = [_max_abs(c) for c in currents]
    return out


def _timing(log: LoadedLog, sig: Signals, first: int) -> dict[str, Any]:
    s = log.data.samples[first:]
    fb = sig.has_feedback[first:]
    rx = s["rx_time_ns"].view(np.int64)  # ns since an epoch: below 2**63
    tx = s["tx_time_ns"].view(np.int64)
    seq = s["seq"].astype(np.int64)
    latency = (tx - rx)[fb & (tx >= rx)]  # a sample that sent no command keeps tx 0
    pair = fb[1:] & fb[:-1] & (np.diff(seq) == 1)
    jitter = np.abs(np.diff(rx) - log.period_ns)[pair]
    return {
        "latency_us": distribution(latency, 1e-3),
        "period_jitter_us": distribution(jitter, 1e-3),
        "compute_us": distribution(s["compute_ns"], 1e-3),
    }


def _int_or_none(text: str | None) -> int | None:
    try:
        return int(text) if text is not None else None
    except ValueError:
        return None


@dataclass
class WindowFigures:
    """What the metrics of a window are computed from, however the log was read: held in memory
    (:func:`compute_metrics`) or streamed (:mod:`dob_hil.analysis.streamed`)."""

    samples: int  # in the window
    t_first_s: float | None  # first and last sample instants of the window (None: empty)
    t_last_s: float | None
    log_end_s: float  # the last sample's instant (0 without samples)
    tracking: tuple[float | None, float | None, str, int]  # rms, max, source, samples used
    disturbance: dict[str, Any]
    saturated: int
    overruns: int
    feedback_missing: int
    skipped: int
    dropped: int
    timing: dict[str, Any]
    bus: dict[str, Any] | None
    truth_samples: int
    extra: dict[str, Any] = field(default_factory=dict)  # per axis (_per_axis), timing_percentiles
    out_of_sequence: int = 0  # samples whose seq does not exceed the previous one's
    time_back: int = 0  # samples of the whole log whose time_ns is below the previous sample's
    non_finite: int = 0  # samples of the window with a non-finite value (non_finite_rows)
    log_samples: int | None = None  # samples in the whole log (None: not counted)


def out_of_sequence(steps: npt.NDArray[np.int64]) -> int:
    """How many consecutive-sample sequence steps are not increasing (duplicated or reordered)."""
    return int(np.count_nonzero(steps <= 0))


def compute_metrics(log: LoadedLog, from_s: float, signals: Signals | None = None) -> dict[str, Any]:
    """The metrics dictionary of the module docstring."""
    sig = signals if signals is not None else derive_signals(log)
    s = log.data.samples
    first = window_start(sig.t_s, from_s)
    w = slice(first, None)
    n = len(s) - first
    flags = s["flags"][w]
    seq = s["seq"][w].astype(np.int64)
    skipped, dropped = gap_accounting(seq, log.data.events)
    t = sig.t_s[w]
    figures = WindowFigures(
        samples=n,
        t_first_s=float(t[0]) if n else None,
        t_last_s=float(t[-1]) if n else None,
        log_end_s=float(sig.t_s[-1]) if len(s) else 0.0,
        tracking=_tracking(sig, w),
        disturbance=_disturbance(log, sig, w),
        saturated=int(np.count_nonzero(flags & FLAG_SATURATED)),
        overruns=int(np.count_nonzero(flags & FLAG_OVERRUN)),
        feedback_missing=int(np.count_nonzero(~sig.has_feedback[w])),
        skipped=skipped,
        dropped=dropped,
        timing=_timing(log, sig, first),
        bus=bus_load(s, log.data.frames, log.data.fd_frames, first, log.period_ns, log.bitrate_bps),
        truth_samples=int(np.count_nonzero(sig.has_truth[w])),
        extra={**_per_axis(log, sig, w), "timing_percentiles": "exact"},
        out_of_sequence=out_of_sequence(np.diff(seq)),
        time_back=time_steps_back(s["time_ns"].view(np.int64)),
        non_finite=non_finite_rows(s[w]),
        log_samples=len(s),
    )
    return assemble_metrics(log, from_s, figures)


def assemble_metrics(log: LoadedLog, from_s: float, f: WindowFigures) -> dict[str, Any]:
    """The metrics dictionary of the module docstring from the window's figures."""
    n = f.samples
    warnings = list(log.warnings)
    notes: list[str] = []
    if f.log_samples == 0:
        warnings.append("the log holds no samples: nothing to measure")
    elif n == 0:
        warnings.append(
            f"no samples in the window: --from {from_s:g} s is past the log's end ({f.log_end_s:.4f} s)"
        )
    if f.non_finite:
        warnings.append(
            f"{f.non_finite} samples hold non-finite values (NaN or inf in {', '.join(FINITE_FIELDS)}): "
            "left out of the figures that use them"
        )
    if f.time_back:
        warnings.append(
            f"{f.time_back} samples' time goes back (time_ns below the previous sample's): the log's "
            "clock is damaged; the window starts at the first sample at or after --from"
        )
    if f.out_of_sequence:
        warnings.append(
            f"{f.out_of_sequence} samples out of sequence (sequence number not above the previous "
            "sample's): duplicated or reordered log records; the dropped count may be off by as many"
        )
    rms, emax, source, used = f.tracking
    if source == "measured":
        notes.append("no ground truth: tracking error against the measured output")
    if log.mode == "lockstep":
        notes.append(
            "lockstep run: latency and jitter are host wall-clock times of a simulation "
            "running faster than real time, not real-time behaviour"
        )
    has_window = n > 0 and f.t_first_s is not None and f.t_last_s is not None
    metrics: dict[str, Any] = {
        "file": str(log.path),
        "scenario": log.scenario,
        "mode": log.mode,
        "dob_enabled": log.dob_enabled,
        "complete": bool(log.data.complete) and f.dropped == 0 and f.out_of_sequence == 0,
        "window_start_s": f.t_first_s if has_window else None,
        "samples": n,
        "duration_s": (
            float(f.t_last_s - f.t_first_s) + log.period_ns * 1e-9  # type: ignore[operator]
            if has_window
            else 0.0
        ),
        "tracking_error_rms": rms,
        "tracking_error_max": emax,
        "tracking_error_source": source,
        **f.disturbance,
        "saturated_fraction": float(f.saturated) / n if n else None,
        "overruns": f.overruns,
        "feedback_missing": f.feedback_missing,
        "skipped_samples": f.skipped,
        "dropped_samples": f.dropped,
        "out_of_sequence_samples": f.out_of_sequence,
        "non_finite_samples": f.non_finite,
        "log_dropped_records": _int_or_none(log.summary.get("dropped_records")),
        **f.timing,
        "bus_load": f.bus,
        "truth_samples": f.truth_samples,
        "tracking_error_samples": used,
        **f.extra,
        "notes": notes,
        "warnings": warnings,
    }
    return metrics
