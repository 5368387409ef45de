"""``replay --verify`` streamed and vectorised: bounded memory, hundreds of thousands of samples/s.

The chained re-run of :mod:`rerun` carries the controller's own state from sample to sample, one
Python step each. When the log is identical to what the controller computes, that chain equals
the log at every sample, so the same verdict follows from checking every sample *locally*: from
the logged ``x_bar`` of sample i, recompute the update, the quantizer and the prediction, and
compare them with the logged fields of sample i and with the logged ``x_bar`` of sample i + 1
(by induction the chain then never leaves the log). Each check is the generated straight-line
step (:func:`dob_hil.control.step.compile_step`) evaluated on numpy columns instead of floats:
the same IEEE-754 operations in the same order, so bit for bit the same values; the quantizer is
:class:`~dob_hil.link.native.DacQuantizer`'s rule vectorised (and checked against it on its
boundaries before use). Missing feedback, lost slots, the hold/extrapolate/zero policies and
unexplained sequence gaps (a restart from the logged ``x_bar``) follow :func:`rerun.rerun`.

The samples are read block by block (:func:`dob_hil.log.reader.iter_channel`), with the few
values the chain carries across a block (held command, last measured output, consecutive missing
count, the prediction for the next block's first sample) passed on, so memory does not grow with
the log. :func:`verify_streaming` returns None when this path cannot give the verdict exactly as
:func:`dob_hil.analysis.replay.verify` does -- a mismatch (whose reporting follows the chain), or
a log without the run metadata it needs -- and the caller then runs the chained path.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from dob_hil.analysis.loaded import LoadedLog
from dob_hil.analysis.replay import VerifyResult, logged_drive, logged_missing_policy
from dob_hil.analysis.rerun import MissingPolicy, explained_gaps
from dob_hil.config import DriveConfig
from dob_hil.control.reference import Reference, make_reference
from dob_hil.control.step import Gains, StepFunctions, compile_step
from dob_hil.errors import DobHilError
from dob_hil.link.native import DacQuantizer
from dob_hil.log.reader import iter_channel
from dob_hil.log.schemas import FLAG_FEEDBACK_MISSING, FLAG_SATURATED, TOPIC_SAMPLE

FloatArray = npt.NDArray[np.float64]
VERIFIED_FIELDS = ("position", "x_hat", "x_bar", "u_fb", "u_dist", "u_cmd_a", "u_applied_a", "dac_counts",
                   "saturated")  # fmt: skip


class VectorQuantizer:
    """:meth:`DacQuantizer.quantize` on arrays (one axis): codes, applied currents, saturated."""

    def __init__(self, drive: DriveConfig) -> None:
        self.scalar = DacQuantizer(drive)
        self.lsb_A = self.scalar.dac_lsb_A
        self.limit = self.scalar.limit_code
        self.round_limit = self.limit + 0.5
        edge = float(np.nextafter(self.round_limit, 0.0))
        probes = [0.0, -0.0, 0.5, -0.5, 1.5, -1.5, 2.5, self.round_limit, -self.round_limit, edge, -edge]
        u = np.asarray([x * self.lsb_A for x in probes] + [np.nan, np.inf, -np.inf], dtype=np.float64)
        codes, applied, sat = self(u)
        for i, value in enumerate(u.tolist()):
            (code,), (amps,), saturated = self.scalar.quantize((value,))
            if (code, amps, saturated) != (int(codes[i]), float(applied[i]), bool(sat[i])):
                raise ValueError(f"the vectorised quantizer differs from DacQuantizer at {value!r}")

    def __call__(self, u: FloatArray) -> tuple[npt.NDArray[np.int64], FloatArray, npt.NDArray[np.bool_]]:
        finite = np.isfinite(u)
        x = np.where(finite, u, 0.0) / self.lsb_A
        hi, lo = x >= self.round_limit, x <= -self.round_limit
        ax = np.abs(x)
        q = np.trunc(ax)
        mag = q + ((ax - q) >= 0.5)
        code = np.where(x >= 0.0, mag, -mag)
        code = np.where(hi, self.limit, np.where(lo, -self.limit, code)).astype(np.int64)
        code[~finite] = 0
        applied = code.astype(np.float64) * self.lsb_A
        return code, applied, hi | lo | ~finite


@dataclass
class _Carry:
    """What the chain carries from one block to the next."""

    held_codes: npt.NDArray[np.int64]
    held_applied: FloatArray
    held_u_dist: FloatArray
    last_y: FloatArray | None  # the last measured output (None before any feedback)
    consecutive: int  # missing (not lost) samples in a row
    next_x_bar: FloatArray | None  # the prediction for the next sample
    prev_seq: int | None


def _columns(a: npt.NDArray[Any], width: int) -> list[FloatArray]:
    return [np.ascontiguousarray(a[:, j]) for j in range(width)]


def _stack(cols: tuple[Any, ...], n: int) -> FloatArray:
    return np.column_stack([np.broadcast_to(np.asarray(c, dtype=np.float64), (n,)) for c in cols])


def _last_index(mask: npt.NDArray[np.bool_]) -> npt.NDArray[np.int64]:
    """For each i, the largest j < i with mask[j] (or -1)."""
    idx = np.where(mask, np.arange(len(mask)), -1)
    run = np.maximum.accumulate(idx)
    out = np.empty(len(mask), dtype=np.int64)
    out[0] = -1
    out[1:] = run[:-1]
    return out


def _c_times(C_rows: list[tuple[float, ...]], x_bar: FloatArray) -> FloatArray:
    """C x_bar summed left to right from 0, as ``sum(c * x ...)`` in :func:`rerun.rerun`."""
    out = np.empty((len(x_bar), len(C_rows)), dtype=np.float64)
    for i, row in enumerate(C_rows):
        acc: Any = 0
        for j, c in enumerate(row):
            acc = acc + c * x_bar[:, j]
        out[:, i] = acc
    return out


def reference_rows(reference: Reference, seq: npt.NDArray[np.int64]) -> FloatArray:
    """``reference.at(k)`` for each k of ``seq`` (bit for bit): one vectorised
    :meth:`Reference.block` over the span of ``seq`` when it is not much longer than the block
    (gaps are few), else one ``at`` per sample."""
    n = len(seq)
    if n == 0:
        return np.zeros((0, 0), dtype=np.float64)
    lo, hi = int(seq.min()), int(seq.max())
    span = hi - lo + 1
    if span <= 4 * n + 1024:
        return np.asarray(reference.block(lo, span), dtype=np.float64)[seq - lo]
    return np.asarray([reference.at(k) for k in seq.tolist()], dtype=np.float64)


def _block(
    s: npt.NDArray[np.void],
    step: StepFunctions,
    quantize: VectorQuantizer,
    C_rows: list[tuple[float, ...]],
    missing: MissingPolicy,
    resumed: set[int],
    carry: _Carry,
    resyncs: list[int],
    reference: Reference | None,
) -> bool:
    """Check one block; True if every sample matches (carry updated for the next block)."""
    n = len(s)
    N, m, p = step.n_states, step.n_inputs, step.n_outputs
    if m != 1:
        return False
    flags = s["flags"]
    is_missing = (flags & FLAG_FEEDBACK_MISSING) != 0
    lost = is_missing & (s["tx_time_ns"] == 0)
    x_bar = np.asarray(s["x_bar"], dtype=np.float64).reshape(n, N)
    position = np.asarray(s["position"], dtype=np.float64).reshape(n, p)
    x_ref = np.asarray(s["x_ref"], dtype=np.float64).reshape(n, N)
    seq = s["seq"].astype(np.int64)

    # the chained x_bar: the previous prediction, except at a restart (unexplained gap)
    prev = np.empty(n, dtype=np.int64)
    prev[0] = carry.prev_seq if carry.prev_seq is not None else -1
    prev[1:] = seq[:-1]
    restart = prev + 1 != seq
    if restart.any():  # a gap: a restart unless the runner explained it
        at = np.flatnonzero(restart)
        restart[at] = np.isin(seq[at], np.fromiter(resumed, dtype=np.int64), invert=True)
    if carry.prev_seq is None:
        restart[0] = False
    resyncs.extend(seq[restart].tolist())

    # the estimator's input
    measured = ~is_missing
    last_meas = _last_index(measured)
    c_x_bar = _c_times(C_rows, x_bar)
    have_last = (last_meas >= 0) | (carry.last_y is not None)
    last_y = np.empty((n, p), dtype=np.float64)
    inside = last_meas >= 0
    last_y[inside] = position[last_meas[inside]]
    if carry.last_y is not None:
        last_y[~inside] = carry.last_y
    hold = (missing.policy == "hold") & have_last
    y = np.where(measured[:, None], position, np.where((hold & ~lost)[:, None], last_y, c_x_bar))

    update: Any = step.update  # the generated step, here on numpy columns
    predict: Any = step.predict
    out = update(tuple(_columns(x_bar, N)), tuple(_columns(y, p)), tuple(_columns(x_ref, N)))
    x_hat = _stack(out.x_hat, n)
    u_fb = _stack(out.u_fb, n)
    u_dist = _stack(out.u_dist, n)
    u_cmd = _stack(out.u_cmd, n)

    # consecutive missing (lost samples neither count nor reset), zeroing rules
    counted = ~lost
    miss_c = is_missing & counted
    csum = np.cumsum(miss_c.astype(np.int64))
    reset_at = np.where(counted & measured, csum, 0)
    base = np.maximum.accumulate(reset_at)
    had_reset = np.maximum.accumulate(counted & measured)
    consecutive = csum - base + np.where(had_reset, 0, carry.consecutive)
    zero_out = miss_c & (
        (missing.policy == "zero") | (consecutive > missing.max_missing_periods) | ~have_last
    )
    u_cmd = np.where(zero_out[:, None], 0.0, u_cmd)
    codes, applied, saturated = quantize(u_cmd[:, 0])
    codes2, applied2 = codes[:, None], applied[:, None]

    # lost slots: the held command (from the last sample that sent one)
    last_sent = _last_index(counted)
    held_codes = np.empty((n, m), dtype=np.int64)
    held_applied = np.empty((n, m), dtype=np.float64)
    held_u_dist = np.empty((n, m), dtype=np.float64)
    ok = last_sent >= 0
    held_codes[ok], held_applied[ok], held_u_dist[ok] = (
        codes2[last_sent[ok]],
        applied2[last_sent[ok]],
        u_dist[last_sent[ok]],
    )
    held_codes[~ok], held_applied[~ok], held_u_dist[~ok] = (
        carry.held_codes,
        carry.held_applied,
        carry.held_u_dist,
    )
    L = lost[:, None]
    u_dist_out = np.where(L, held_u_dist, u_dist)
    u_cmd_out = np.where(L, held_applied, u_cmd)
    applied_out = np.where(L, held_applied, applied2)
    codes_out = np.where(L, held_codes, codes2)
    sat_out = np.where(lost, False, saturated)

    # predictions: x_bar' of each sample, against the next sample's logged x_bar
    px = np.where(L, x_bar, x_hat)
    pred = _stack(predict(tuple(_columns(px, N)), tuple(_columns(applied_out, m)),
                               tuple(_columns(u_dist_out, m))), n)  # fmt: skip
    chained = np.empty_like(x_bar)
    chained[1:] = pred[:-1]
    chained[0] = carry.next_x_bar if carry.next_x_bar is not None else x_bar[0]
    chained[restart] = x_bar[restart]

    def same(a: npt.NDArray[Any], b: npt.NDArray[Any]) -> bool:
        a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
        if a.dtype == np.float64 and b.dtype == np.float64:
            return bool(np.array_equal(a.view(np.uint64), b.view(np.uint64)))
        return bool(np.array_equal(a.astype(np.int64), b.astype(np.int64)))

    checks = (
        same(position, y),
        same(x_bar, chained),
        same(np.asarray(s["x_hat"], dtype=np.float64).reshape(n, N), x_hat),
        same(np.asarray(s["u_fb"], dtype=np.float64).reshape(n, m), u_fb),
        same(np.asarray(s["u_dist"], dtype=np.float64).reshape(n, m), u_dist_out),
        same(np.asarray(s["u_cmd_a"], dtype=np.float64).reshape(n, m), u_cmd_out),
        same(np.asarray(s["u_applied_a"], dtype=np.float64).reshape(n, m), applied_out),
        same(np.asarray(s["dac_counts"]).reshape(n, m), codes_out),
        bool(np.array_equal((flags & FLAG_SATURATED) != 0, sat_out)),
        reference is None or same(x_ref, reference_rows(reference, seq)),
    )
    if not all(checks):
        return False
    # carry on
    sent = np.flatnonzero(counted)
    if len(sent):
        j = int(sent[-1])
        carry.held_codes, carry.held_applied, carry.held_u_dist = codes2[j], applied2[j], u_dist[j]
    meas = np.flatnonzero(measured)
    if len(meas):
        carry.last_y = position[int(meas[-1])].copy()
    if len(sent):
        carry.consecutive = int(consecutive[int(sent[-1])])
    carry.next_x_bar = pred[-1].copy()
    carry.prev_seq = int(seq[-1])
    return True


def _blocks(path: Path) -> Iterator[npt.NDArray[np.void]]:
    yield from iter_channel(path, TOPIC_SAMPLE)


def verify_streaming(log: LoadedLog) -> VerifyResult | None:
    """The verdict of :func:`dob_hil.analysis.replay.verify` for an identical log, streamed (module
    docstring); None when the chained path must decide. ``log`` needs its events and metadata only
    (load it with ``topics=[TOPIC_EVENT]``)."""
    if log.design is None or log.run.get("dob_enabled") not in ("true", "false"):
        return None
    notes: list[str] = []
    fields = list(VERIFIED_FIELDS)
    reference: Reference | None = None
    if log.config is not None:
        try:
            reference = make_reference(
                log.config.reference, log.data.layout.n_states, log.config.plant.period_s
            )
            fields.append("x_ref")
        except DobHilError:
            notes.append("the reference could not be rebuilt from the config; x_ref not checked")
    drive = logged_drive(log, notes)
    missing = logged_missing_policy(log, notes)
    design = log.design
    step = compile_step(
        Gains(design.Phi, design.Gam, design.C, design.Lc, design.Kc, design.Kdist), log.dob_enabled
    )
    try:
        quantize = VectorQuantizer(drive)
    except ValueError:
        return None
    C_rows = [tuple(float(c) for c in row) for row in design.C]
    m = step.n_inputs
    carry = _Carry(np.zeros(m, dtype=np.int64), np.zeros(m), np.zeros(m), None, 0, None, None)
    resumed = explained_gaps(log.data.events)
    resyncs: list[int] = []
    total = 0
    for block in _blocks(log.path):
        if not _block(block, step, quantize, C_rows, missing, resumed, carry, resyncs, reference):
            return None
        total += len(block)
    if resyncs:
        notes.append(f"{len(resyncs)} unexplained sequence gap(s): re-started from the logged x_bar there")
    return VerifyResult(
        samples=total,
        dob_enabled=log.dob_enabled,
        fields=fields,
        identical=total > 0,
        mismatched_samples=0,
        mismatches_by_field=dict.fromkeys(fields, 0),
        first_mismatches=[],
        first_mismatch_seq=None,
        resyncs=resyncs,
        notes=notes,
    )
