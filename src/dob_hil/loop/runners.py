"""The two schedules of the loop: lockstep (with the embedded simulated drive) and real time.

Both call the same :class:`~dob_hil.loop.cycle.ControlCycle`; they differ only in how a sample
instant comes about.

- Lockstep: the embedded drive advances one period per command; ``drive.service()`` runs between
  the command and the next receive, in this thread. Deterministic, as fast as the CPU allows.
  ``time_ns`` is the simulated sample instant ``k * period_ns``. A command that never reached the
  drive still costs it one period (``advance_period``: held current, a watchdog count). Samples
  without feedback follow the cycle's missing-feedback policy; each gap is logged as a
  ``feedback_lost`` event when feedback resumes.
- Real time: the drive is the clock (it sends feedback every period) and its sequence number
  the sample index. Sample k's nominal instant is ``anchor + k * period_ns``, where the anchor
  follows the drive's clock with a slow first-order tracker (64 samples) so that drift between
  the two clocks does not accumulate; lateness is measured against it. Overruns (newer feedback
  already queued when one is read) skip ahead to the newest; gaps are filled with model-only
  samples; every skip is counted and reported as an event (see :func:`run_realtime`). The gap is
  counted from the sequence number; periods that passed by the host's clock beyond what the
  sequence accounts for (a stall of 128 periods or more, where the 8-bit sequence number may have
  wrapped) are counted from time and reported as a ``stall`` event. Sample log times never step
  back (a re-anchor that would move them back holds them at the last one).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

from dob_hil.errors import DriveFault
from dob_hil.link.base import DriveLink
from dob_hil.loop.cycle import ControlCycle

SEQ_MODULO = 256


def _fault_message(link: object, seq: int) -> str:
    """The drive's fault, named by the link where it can (``fault_description``)."""
    detail = getattr(link, "fault_description", None)
    return f"the drive reports a fault (feedback seq {seq})" + (f": {detail}" if detail else "")


TIMEOUT_HINT = (
    "; on a busy machine widen --feedback-timeout-periods (drive.feedback_timeout_periods) and the "
    "drive's watchdog (--watchdog-periods), or give the loop and the drive a CPU each"
)


class LoopLog(Protocol):
    """What the runners write besides samples: events (``time_ns`` None: the run's clock now) and
    the writer's flush (see :class:`dob_hil.loop.timeline.LoopLog`)."""

    def event(
        self, time_ns: int | None, level: str, kind: str, message: str, data: Mapping[str, Any] | None = None
    ) -> None: ...

    def flush(self, force: bool = False) -> None: ...


class StopRequest(Protocol):
    @property
    def requested(self) -> str | None: ...


class LockstepDrive(Protocol):
    def service(self) -> int: ...

    def advance_period(self) -> None: ...

    @property
    def period_index(self) -> int: ...


@dataclass(frozen=True)
class LoopLimits:
    n_samples: int
    period_ns: int
    timeout_periods: int  # host timeout: this many consecutive periods without feedback ends the run


def _seq_delta(seq: int, expected: int) -> int:
    """How far ``seq`` is ahead of ``expected`` (mod 256, in -128..127)."""
    return (seq - expected + 128) % SEQ_MODULO - 128


def run_lockstep(
    cycle: ControlCycle,
    link: DriveLink,
    drive: LockstepDrive,
    log: LoopLog,
    limits: LoopLimits,
    stop: StopRequest,
    progress: Callable[[int], None] | None = None,
) -> str:
    """Run ``limits.n_samples`` samples; returns the exit reason ("completed" or the stop reason)."""
    period_ns = limits.period_ns
    expected_seq: int | None = None
    missing_run = 0
    on_feedback, on_missing, receive, service = (
        cycle.on_feedback,
        cycle.on_missing,
        link.receive_feedback,
        drive.service,
    )
    flush = log.flush
    progress_every = 4096
    for k in range(limits.n_samples):
        reason = stop.requested
        if reason is not None:
            return reason
        service()
        fb = receive(0)
        time_ns = k * period_ns
        if fb is None and drive.period_index < k:
            # the command of sample k - 1 never reached the drive: its clock runs on without one
            # (the held current, a watchdog count), as a drive on its own crystal would
            drive.advance_period()
            fb = receive(0)
        if fb is None:
            missing_run += 1
            if missing_run >= limits.timeout_periods:
                raise DriveFault(
                    f"no feedback from the drive for {missing_run} periods (host timeout){TIMEOUT_HINT}"
                )
            answer = 0 if expected_seq is None else expected_seq
            on_missing(k, time_ns, answer, 0, False)
        else:
            if missing_run:
                _log_gap(log, k, missing_run)
                missing_run = 0
            if fb.fault:
                raise DriveFault(_fault_message(link, fb.seq))
            on_feedback(k, time_ns, fb, 0, False)
            expected_seq = fb.seq
        if expected_seq is not None:
            expected_seq = (expected_seq + 1) % SEQ_MODULO
        if k % progress_every == 0:
            flush()
            if progress is not None:
                progress(k)
    service()  # let the drive take the last command
    return "completed"


def _log_gap(log: LoopLog, k: int, count: int) -> None:
    """Lockstep: the event for ``count`` samples before ``k`` that had no feedback."""
    log.event(
        None,
        "warning",
        "feedback_lost",
        f"no feedback for {count} sample(s) before sample {k}",
        {"first_sample": k - count, "count": count},
    )


def _unsequenced_periods(delta: int, since_ns: int, period_ns: int) -> tuple[int, int]:
    """(gap, excess) for a feedback ``delta`` (mod 256, -128..127) sequence numbers from the
    expected one that came ``since_ns`` after the previous sample's instant.

    When the host's clock says that half the 8-bit range or more passed (a stall: the sequence
    number may have wrapped), a negative ``delta`` is taken as ``delta + 256`` ahead (not stale),
    and ``excess`` is the periods beyond what the sequence accounts for; else ``(delta, 0)``. The
    excess is not filled as samples (a drive stalled as long as the host, both starved on one
    machine, gives it too, and the sample index stays the drive's sequence): it is counted and
    reported (``CycleStats.unsequenced_periods``, a ``stall`` event)."""
    by_time = round(since_ns / period_ns) - 1  # periods passed beyond the expected one
    if by_time < SEQ_MODULO // 2:
        return delta, 0
    gap = delta + SEQ_MODULO if delta < 0 else delta
    excess = by_time - gap
    return gap, excess if excess >= SEQ_MODULO // 2 else 0


def run_realtime(
    cycle: ControlCycle,
    link: DriveLink,
    log: LoopLog,
    limits: LoopLimits,
    stop: StopRequest,
    first_feedback_timeout_ns: int = 2_000_000_000,
    clock_ns: Callable[[], int] = time.monotonic_ns,
    progress: Callable[[int], None] | None = None,
) -> str:
    """Answer the drive's feedback in real time for ``limits.n_samples`` periods.

    The drive is the clock and its sequence number the sample index: the host never advances on
    its own clock, so a stall of either side never makes the two disagree about which sample is
    due. Each feedback is answered at once. If newer feedback is already queued when one is read
    late (more than half a period after its nominal instant: the host fell behind), only the
    newest is answered (skip ahead, no burst of stale commands) and the sample is flagged as an
    overrun. A sequence gap (frames lost, or skipped) is filled
    with :meth:`ControlCycle.on_lost` samples: the model is advanced over each with the input the
    drive held and no measurement, so it stays in step with the plant and the log has every
    sample. No feedback for ``timeout_periods`` periods ends the run (host timeout); the drive's
    own watchdog covers the commands it does not receive.
    """
    period_ns = limits.period_ns
    timeout_ns = limits.timeout_periods * period_ns
    receive = link.receive_feedback
    fb = receive(first_feedback_timeout_ns)
    if fb is None:
        raise DriveFault(
            f"no feedback from the drive within {first_feedback_timeout_ns / 1e9:g} s of enabling"
        )
    while (newer := receive(0)) is not None:  # start from the newest feedback queued
        fb = newer
    if clock_ns() - fb.rx_time_ns > period_ns:
        # an old one (kept from the enable handshake): the anchor needs a fresh reading
        fb = receive(first_feedback_timeout_ns) or fb
    anchor_ns = fb.rx_time_ns
    expected_seq = fb.seq
    last_rx_ns = fb.rx_time_ns
    last_log_ns = 0  # the samples' log time never steps back
    half_period_ns = period_ns // 2
    # below this many ns since the last instant no stall can hide periods (by_time < 128)
    stall_check_ns = (SEQ_MODULO // 2) * period_ns
    k = 0
    while k < limits.n_samples:
        reason = stop.requested
        if reason is not None:
            return reason
        if fb is None:
            # read first, judge after: frames queued while this process was stalled still count
            remaining_ns = last_rx_ns + timeout_ns - clock_ns()
            fb = receive(min(max(remaining_ns, 0), 20 * period_ns))  # bounded: a stop is seen
            if fb is None:
                if clock_ns() - last_rx_ns >= timeout_ns:
                    raise DriveFault(
                        f"no feedback from the drive for {limits.timeout_periods} periods "
                        f"({timeout_ns / 1e6:g} ms: host timeout){TIMEOUT_HINT}"
                    )
                continue
        if fb.fault:
            raise DriveFault(_fault_message(link, fb.seq))
        rx_ns = last_rx_ns = fb.rx_time_ns
        overrun = False
        instant_ns = anchor_ns + k * period_ns
        if rx_ns - instant_ns > half_period_ns:
            # read late: newer feedback may be queued (on time, none can have been sent yet, so
            # the common case costs no extra receive)
            while (newer := receive(0)) is not None:
                fb, overrun = newer, True
            rx_ns = fb.rx_time_ns
        # with the time count: how many periods after sample k - 1's nominal instant (on the
        # drive's clock, as tracked by the anchor) this feedback came
        since_ns = rx_ns - (instant_ns - period_ns)
        delta = (fb.seq - expected_seq + 128) % SEQ_MODULO - 128  # _seq_delta, inline
        if since_ns < stall_check_ns:  # fewer periods than a stall needs: _unsequenced_periods
            excess = 0  # would give (delta, 0)
        else:
            delta, excess = _unsequenced_periods(delta, since_ns, period_ns)
        if excess:
            cycle.stats.unsequenced_periods += excess
            log.event(
                clock_ns(),
                "warning",
                "stall",
                f"{excess} period(s) before seq {fb.seq} passed beyond the {delta} its "
                "sequence number accounts for (a stall of this host, or of both sides)",
                {"sample": k, "count": excess},
            )
        if delta < 0:  # older than expected: a duplicate or a reordered frame
            log.event(clock_ns(), "warning", "stale_feedback", f"feedback seq {fb.seq} is {-delta} behind")
            fb = None
            continue
        if delta > 0:
            kind = "overrun_skip" if overrun else "feedback_lost"
            fill = min(delta, limits.n_samples - k)  # a gap may run past the end of the run
            log.event(
                clock_ns(),
                "warning",
                kind,
                f"{delta} sample(s) before seq {fb.seq} {'skipped' if overrun else 'lost'}",
                {"first_sample": k, "count": fill},
            )
            cycle.stats.skipped += fill
            for _ in range(fill):
                t = anchor_ns + k * period_ns
                last_log_ns = t if t > last_log_ns else last_log_ns
                cycle.on_lost(k, last_log_ns, expected_seq)
                k += 1
                expected_seq = (expected_seq + 1) % SEQ_MODULO
            if k >= limits.n_samples:
                break
        instant_ns = anchor_ns + k * period_ns  # (k moved on if a gap was filled)
        lateness_ns = rx_ns - instant_ns
        if -period_ns < lateness_ns < period_ns:
            anchor_ns += lateness_ns >> 6  # track the drive's clock (first order, 64 samples)
        else:
            anchor_ns = rx_ns - k * period_ns  # the drive's clock jumped: re-anchor
        last_log_ns = instant_ns if instant_ns > last_log_ns else last_log_ns
        cycle.on_feedback(k, last_log_ns, fb, lateness_ns, overrun)
        log.flush()
        k += 1
        expected_seq = (fb.seq + 1) % SEQ_MODULO
        fb = None
        if progress is not None and k % 3333 == 0:
            progress(k)
    return "completed"
