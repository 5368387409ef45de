"""One control cycle: feedback in, pure step, command out, sample to the logger.

This is the part shared by the lockstep and the real-time runners. It owns the controller state
(``x_bar``) and the missing-feedback policy; it never touches frames (the link does) and never
writes a file (the log writer's process does).

Missing or stale feedback (``run.missing_feedback_policy``, bounded by ``run.max_missing_periods``
consecutive samples):

- ``hold``: the estimator is given the last measured output again;
- ``extrapolate``: the measurement update is skipped (``x_hat = x_bar``: the model's prediction);
- ``zero``: zero current is commanded for that sample (the estimator still predicts with it).

Beyond ``max_missing_periods`` consecutive missing samples the cycle commands zero current; at
``drive.feedback_timeout_periods`` the runner stops the run (host timeout) with the drive at zero.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

from dob_hil.control.reference import Reference
from dob_hil.control.step import StepFunctions
from dob_hil.link.base import DriveLink, Feedback
from dob_hil.log import LogWriter
from dob_hil.log.schemas import FLAG_DOB_ON, FLAG_OVERRUN, FLAG_SATURATED
from dob_hil.log.schemas import FLAG_FEEDBACK_MISSING as FLAG_MISSING


@dataclass
class CycleStats:
    samples: int = 0
    saturated: int = 0
    missing: int = 0
    overruns: int = 0
    skipped: int = 0
    unsequenced_periods: int = 0  # real time: periods a stall hid from the sequence number (by time)
    max_consecutive_missing: int = 0
    max_abs_applied_A: float = 0.0
    compute_ns_max: int = 0
    events: dict[str, int] = field(default_factory=dict)


class ControlCycle:
    """Holds the controller state; :meth:`on_feedback` and :meth:`on_missing` run one sample each."""

    def __init__(
        self,
        step: StepFunctions,
        reference: Reference,
        link: DriveLink,
        log: LogWriter,
        *,
        dob_enabled: bool,
        missing_policy: str,
        max_missing_periods: int,
        C_rows: tuple[tuple[float, ...], ...],
        initial_x_bar: tuple[float, ...] | None = None,
        clock_ns: Callable[[], int] = time.perf_counter_ns,
        sim_time: bool = False,
        check: Callable[[int, tuple[float, ...], tuple[float, ...]], None] | None = None,
    ) -> None:
        """``sim_time``: lockstep, where the sample instant ``time_ns`` is simulated time; the
        sample's rx and tx times are logged on that clock too (the exchange takes no simulated
        time). ``check(k, position, x_ref)``: called after each command is sent (the safety
        envelope)."""
        self._update = step.update
        self._predict = step.predict
        self._ref_at = reference.at
        self._link = link
        self._quantize = link.quantize  # pre-bound: the per-period path
        self._send_command = link.send_command
        self._log = log
        self._log_sample = log.sample
        self._clock_ns = clock_ns
        self.n_states = step.n_states
        self.n_inputs = step.n_inputs
        self.n_outputs = step.n_outputs
        self.x_bar: tuple[float, ...] = initial_x_bar or (0.0,) * step.n_states
        self._dob_flag = FLAG_DOB_ON if dob_enabled else 0
        self._policy = missing_policy
        self._max_missing = max_missing_periods
        self._zero_u = (0.0,) * step.n_inputs
        self._C_rows = C_rows
        self.consecutive_missing = 0
        self.last_feedback: Feedback | None = None
        self._last_codes: tuple[int, ...] = (0,) * step.n_inputs
        self._last_applied: tuple[float, ...] = self._zero_u
        self._last_u_dist: tuple[float, ...] = self._zero_u
        self._sim_time = sim_time
        self._check = check
        self._one_input = step.n_inputs == 1
        self.stats = CycleStats()

    def on_feedback(self, k: int, time_ns: int, fb: Feedback, lateness_ns: int, overrun: bool) -> None:
        """Sample ``k`` with its feedback: step, quantize, send, log."""
        self.consecutive_missing = 0
        self.last_feedback = fb
        x_ref = self._ref_at(k)
        clock_ns = self._clock_ns
        position = fb.position
        x_bar = self.x_bar
        t0 = clock_ns()
        x_hat, u_fb, u_dist, u_cmd = self._update(x_bar, position, x_ref)
        codes, applied, saturated = self._quantize(u_cmd)
        compute_ns = clock_ns() - t0
        seq = fb.seq
        tx_ns = self._send_command(codes, seq)
        # the prediction for the next sample after the command is out (off the feedback-to-command
        # path); its time counts in compute_ns as well
        t0 = clock_ns()
        self.x_bar = self._predict(x_hat, applied, u_dist)
        compute_ns += clock_ns() - t0
        if self._sim_time:
            rx_ns = tx_ns = time_ns
        else:
            rx_ns = fb.rx_time_ns
        self._last_codes, self._last_applied, self._last_u_dist = codes, applied, u_dist
        flags = self._dob_flag
        s = self.stats
        if saturated:
            flags |= FLAG_SATURATED
            s.saturated += 1
        if overrun:
            flags |= FLAG_OVERRUN
            s.overruns += 1
        self._log_sample(
            time_ns, rx_ns, tx_ns, lateness_ns, fb.counts, position, x_ref, x_hat, x_bar,
            u_fb, u_dist, u_cmd, applied, k, compute_ns, codes, seq, flags,
        )  # fmt: skip
        # _account, inline (the per-period path): comparisons, no builtin calls for one input
        s.samples += 1
        if self._one_input:
            a = applied[0]
            if a > s.max_abs_applied_A or -a > s.max_abs_applied_A:
                s.max_abs_applied_A = a if a >= 0.0 else -a
        else:
            s.max_abs_applied_A = max(s.max_abs_applied_A, *applied, -min(applied))
        if compute_ns > s.compute_ns_max:  # noqa: PLR1730 (a comparison, no call)
            s.compute_ns_max = compute_ns
        if self._check is not None:
            self._check(k, position, x_ref)

    def on_missing(self, k: int, time_ns: int, answers_seq: int, lateness_ns: int, overrun: bool) -> None:
        """Sample ``k`` without (valid) feedback: substitute per the policy, send, log."""
        self.consecutive_missing += 1
        self.stats.missing += 1
        self.stats.max_consecutive_missing = max(self.stats.max_consecutive_missing, self.consecutive_missing)
        x_ref = self._ref_at(k)
        last = self.last_feedback
        x_bar = self.x_bar
        t0 = self._clock_ns()
        if self._policy == "hold" and last is not None:
            y = last.position
        else:  # extrapolate, and the estimator side of zero: the model's own output, innovation 0
            y = tuple(sum(c * x for c, x in zip(row, x_bar, strict=True)) for row in self._C_rows)
        out = self._update(x_bar, y, x_ref)
        zero_out = self._policy == "zero" or self.consecutive_missing > self._max_missing or last is None
        u_cmd = self._zero_u if zero_out else out.u_cmd
        codes, applied, saturated = self._link.quantize(u_cmd)
        # applied - u_dist stays the model's estimate of the plant's net input, also for zero current
        self.x_bar = self._predict(out.x_hat, applied, out.u_dist)
        compute_ns = self._clock_ns() - t0
        tx_ns = self._link.send_command(codes, answers_seq)
        if self._sim_time:
            tx_ns = time_ns
        self._last_codes, self._last_applied, self._last_u_dist = codes, applied, out.u_dist
        counts = last.counts if last is not None else (0,) * self.n_outputs
        flags = self._dob_flag | FLAG_MISSING | (FLAG_SATURATED if saturated else 0)
        flags |= FLAG_OVERRUN if overrun else 0
        self._log.sample(
            time_ns, 0, tx_ns, lateness_ns, counts, y, x_ref, out.x_hat, x_bar,
            out.u_fb, out.u_dist, u_cmd, applied, k, compute_ns, codes, answers_seq % 256, flags,
        )  # fmt: skip
        self._account(applied, saturated, overrun, compute_ns)

    def on_lost(self, k: int, time_ns: int, feedback_seq: int) -> None:
        """Sample ``k`` whose slot has passed unanswered (its feedback lost, or read too late).

        No command is sent (the drive held the last one through that period). The model is
        advanced over the period with that held input and no measurement update, so that it
        stays in step with the plant; the sample is logged flagged as missing, with tx time 0.
        """
        self.stats.missing += 1
        x_bar = self.x_bar
        x_ref = self._ref_at(k)
        y = tuple(sum(c * x for c, x in zip(row, x_bar, strict=True)) for row in self._C_rows)
        out = self._update(x_bar, y, x_ref)  # innovation 0: x_hat = x_bar, u_dist = 0
        applied, u_dist = self._last_applied, self._last_u_dist
        self.x_bar = self._predict(x_bar, applied, u_dist)
        last = self.last_feedback
        counts = last.counts if last is not None else (0,) * self.n_outputs
        self._log.sample(
            time_ns, 0, 0, 0, counts, y, x_ref, out.x_hat, x_bar,
            out.u_fb, u_dist, applied, applied, k, 0, self._last_codes, feedback_seq % 256,
            self._dob_flag | FLAG_MISSING,
        )  # fmt: skip
        self.stats.samples += 1

    def _account(self, applied: tuple[float, ...], saturated: bool, overrun: bool, compute_ns: int) -> None:
        s = self.stats
        s.samples += 1
        if saturated:
            s.saturated += 1
        if overrun:
            s.overruns += 1
        # builtins on the tuple, no generator per sample
        s.max_abs_applied_A = max(s.max_abs_applied_A, *applied, -min(applied))
        s.compute_ns_max = max(s.compute_ns_max, compute_ns)
