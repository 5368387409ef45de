"""Re-running a controller over a log's recorded measurements, exactly as the loop ran it.

The loop's sequence per sample (:mod:`dob_hil.loop.cycle`): ``update(x_bar, y, x_ref)``, the
link's quantizer on ``u_cmd`` (:class:`dob_hil.link.native.DacQuantizer`), then
``x_bar' = predict(x_hat, u_applied, u_dist)``. With missing feedback (flag bit 2) the
estimator gets the substitute of the missing-feedback policy (``hold``: the last measured
output; ``extrapolate``/``zero``: ``C x_bar``), and zero current is commanded under ``zero``,
beyond ``max_missing_periods`` consecutive missing samples, or before any feedback at all.
A sample whose slot passed unanswered (missing, and no command sent: ``tx_time_ns == 0``,
:meth:`dob_hil.loop.cycle.ControlCycle.on_lost`) sends nothing: the model is advanced with the
held input (the last applied current and u_dist) and no measurement update, and the held
command is what the log shows for it.

:func:`rerun` (or :class:`RerunChain`, block by block) starts from the logged first ``x_bar``
and chains its own state from there, so a verify run checks the whole trajectory, not each step
in isolation. At a sequence gap that no
runner event explains (records lost from the log) the chain cannot continue: it restarts from
the logged ``x_bar`` of the next sample and counts a resynchronisation.

One Python step per sample (the generated straight-line step, as in the loop): a few
microseconds each.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from dob_hil.control.step import StepFunctions
from dob_hil.log.schemas import FLAG_FEEDBACK_MISSING

FloatArray = npt.NDArray[np.float64]
Quantize = Callable[[tuple[float, ...]], tuple[tuple[int, ...], tuple[float, ...], bool]]
SKIP_EVENT_KINDS = ("feedback_lost", "overrun_skip")  # runner events: samples skipped on purpose


@dataclass(frozen=True)
class MissingPolicy:
    policy: str  # hold, extrapolate, zero
    max_missing_periods: int


@dataclass(frozen=True)
class Rerun:
    """What the controller computed, one row per logged sample (same shapes as the log's fields)."""

    position: FloatArray  # the output the estimator was given (measured or substituted)
    x_hat: FloatArray
    x_bar: FloatArray  # before the update of the sample, as logged
    u_fb: FloatArray
    u_dist: FloatArray
    u_cmd: FloatArray
    u_applied: FloatArray
    dac_counts: npt.NDArray[np.int64]
    saturated: npt.NDArray[np.bool_]
    resyncs: list[int]  # seq of the samples where the chain restarted from the log


def skip_events(events: list[dict[str, Any]]) -> list[tuple[int, int]]:
    """(first sample, count) of each runner event saying samples were skipped on purpose
    (:data:`SKIP_EVENT_KINDS` with integer ``first_sample`` and ``count``)."""
    out: list[tuple[int, int]] = []
    for ev in events:
        data = ev.get("data")
        if ev.get("kind") in SKIP_EVENT_KINDS and isinstance(data, dict):
            first, count = data.get("first_sample"), data.get("count")
            if isinstance(first, int) and isinstance(count, int):
                out.append((first, count))
    return out


def skipped_ranges(events: list[dict[str, Any]]) -> list[tuple[int, int]]:
    """The half-open sequence ranges the runner skipped on purpose (non-empty ones only)."""
    return [(first, first + count) for first, count in skip_events(events) if count > 0]


def explained_gaps(events: list[dict[str, Any]]) -> set[int]:
    """Sequence numbers at which the runner resumed after samples it skipped on purpose."""
    return {first + count for first, count in skip_events(events)}


class RerunChain:
    """The re-run of the module docstring, fed block by block: the chain's state (the predicted
    ``x_bar``, the held command, the missing-feedback count, the last sequence number) carries
    from one block to the next, so blocks of a streamed log give exactly the rows of one call
    over the whole log."""

    def __init__(
        self,
        step: StepFunctions,
        quantize: Quantize,
        C: FloatArray,
        missing: MissingPolicy,
        events: list[dict[str, Any]],
    ) -> None:
        self.step = step
        self.quantize = quantize
        self.C_rows = [tuple(float(c) for c in row) for row in C]
        self.missing = missing
        self.resumed = explained_gaps(events)
        self.zero_u: tuple[float, ...] = (0.0,) * step.n_inputs
        self.x_bar: tuple[float, ...] | None = None  # None: start from the first logged x_bar
        self.held_codes: tuple[int, ...] = (0,) * step.n_inputs
        self.held_applied, self.held_u_dist = self.zero_u, self.zero_u
        self.last_y: tuple[float, ...] | None = None
        self.consecutive = 0
        self.prev_seq: int | None = None
        self.resyncs: list[int] = []  # over every block fed so far

    def feed(self, samples: npt.NDArray[np.void]) -> Rerun:
        """The rows of the next block of samples (``Rerun.resyncs``: this block's restarts)."""
        n = len(samples)
        step, quantize, C_rows = self.step, self.quantize, self.C_rows
        update, predict = step.update, step.predict
        positions = np.asarray(samples["position"], dtype=np.float64).tolist()
        x_refs = np.asarray(samples["x_ref"], dtype=np.float64).tolist()
        x_bars_log = np.asarray(samples["x_bar"], dtype=np.float64).tolist()
        missing_flags = ((samples["flags"] & FLAG_FEEDBACK_MISSING) != 0).tolist()
        lost_flags = (samples["tx_time_ns"] == 0).tolist()
        seqs = samples["seq"].astype(np.int64).tolist()
        resumed = self.resumed
        zero_u = self.zero_u
        policy, max_missing = self.missing.policy, self.missing.max_missing_periods

        out_y: list[tuple[float, ...]] = []
        out_xh: list[tuple[float, ...]] = []
        out_xb: list[tuple[float, ...]] = []
        out_fb: list[tuple[float, ...]] = []
        out_ud: list[tuple[float, ...]] = []
        out_uc: list[tuple[float, ...]] = []
        out_ua: list[tuple[float, ...]] = []
        out_codes: list[tuple[int, ...]] = []
        out_sat: list[bool] = []
        resyncs: list[int] = []

        x_bar: tuple[float, ...] = (
            self.x_bar if self.x_bar is not None else (tuple(x_bars_log[0]) if n else ())
        )
        held_codes, held_applied, held_u_dist = self.held_codes, self.held_applied, self.held_u_dist
        last_y = self.last_y
        consecutive = self.consecutive
        prev_seq = self.prev_seq
        for i in range(n):
            seq = seqs[i]
            if prev_seq is not None and seq != prev_seq + 1 and seq not in resumed:
                x_bar = tuple(x_bars_log[i])
                resyncs.append(seq)
            prev_seq = seq
            x_ref = x_refs[i]
            if missing_flags[i] and lost_flags[i]:  # slot passed unanswered: nothing sent
                y = tuple(sum(c * x for c, x in zip(row, x_bar, strict=True)) for row in C_rows)
                out = update(x_bar, y, x_ref)
                out_y.append(y)
                out_xh.append(out.x_hat)
                out_xb.append(x_bar)
                out_fb.append(out.u_fb)
                out_ud.append(held_u_dist)
                out_uc.append(held_applied)
                out_ua.append(held_applied)
                out_codes.append(held_codes)
                out_sat.append(False)
                x_bar = predict(x_bar, held_applied, held_u_dist)
                continue
            if missing_flags[i]:
                consecutive += 1
                if policy == "hold" and last_y is not None:
                    y = last_y
                else:
                    y = tuple(sum(c * x for c, x in zip(row, x_bar, strict=True)) for row in C_rows)
                out = update(x_bar, y, x_ref)
                zero_out = policy == "zero" or consecutive > max_missing or last_y is None
                u_cmd = zero_u if zero_out else out.u_cmd
            else:
                consecutive = 0
                y = tuple(positions[i])
                last_y = y
                out = update(x_bar, y, x_ref)
                u_cmd = out.u_cmd
            codes, applied, saturated = quantize(u_cmd)
            held_codes, held_applied, held_u_dist = codes, applied, out.u_dist
            out_y.append(y)
            out_xh.append(out.x_hat)
            out_xb.append(x_bar)
            out_fb.append(out.u_fb)
            out_ud.append(out.u_dist)
            out_uc.append(u_cmd)
            out_ua.append(applied)
            out_codes.append(codes)
            out_sat.append(saturated)
            x_bar = predict(out.x_hat, applied, out.u_dist)
        if n:
            self.x_bar = x_bar
        self.held_codes, self.held_applied, self.held_u_dist = held_codes, held_applied, held_u_dist
        self.last_y, self.consecutive, self.prev_seq = last_y, consecutive, prev_seq
        self.resyncs.extend(resyncs)

        def arr(rows: list[tuple[float, ...]], width: int) -> FloatArray:
            return np.asarray(rows, dtype=np.float64).reshape(n, width)

        N, m, p = step.n_states, step.n_inputs, step.n_outputs
        return Rerun(
            position=arr(out_y, p),
            x_hat=arr(out_xh, N),
            x_bar=arr(out_xb, N),
            u_fb=arr(out_fb, m),
            u_dist=arr(out_ud, m),
            u_cmd=arr(out_uc, m),
            u_applied=arr(out_ua, m),
            dac_counts=np.asarray(out_codes, dtype=np.int64).reshape(n, m),
            saturated=np.asarray(out_sat, dtype=np.bool_),
            resyncs=resyncs,
        )


def rerun(
    step: StepFunctions,
    quantize: Quantize,
    samples: npt.NDArray[np.void],
    C: FloatArray,
    missing: MissingPolicy,
    events: list[dict[str, Any]],
) -> Rerun:
    """Run ``step`` over the samples' recorded outputs and references (module docstring)."""
    return RerunChain(step, quantize, C, missing, events).feed(samples)
