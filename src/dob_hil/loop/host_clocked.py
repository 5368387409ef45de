"""The host-clocked schedules: the host triggers every sample (CANopen SYNC, an RTR, ...).

For profiles with ``Clocking.HOST`` (:mod:`dob_hil.profiles.base`). The runner owns the clock; the
link only knows how to trigger one sample and how to read its answer. What a link offers here
(:class:`HostClockedLink`, profile-neutral on purpose: CiA 402 sends a SYNC, an ODrive-style link
may send remote requests):

- ``send_trigger() -> int``: ask the drive for the sample of this instant (and make it apply the
  setpoint sent since the last trigger); returns the send time (``clock_ns`` of the link). Frames
  still queued from the previous sample are read (and judged stale) first.
- ``receive_feedback(timeout_ns)``: the answer to the last trigger, or None (``DriveLink``).
- ``quantize`` / ``send_command``: as for every ``DriveLink``; the command acts at the next trigger.
- ``drain() -> None``: read and judge the frames already queued, without blocking; the real-time
  runner calls it after each sample, before sleeping, so that little is left to read between a
  deadline and its trigger.
- ``describe_fault(wait_ns) -> str``: what the drive said about its fault (an EMCY code, an error
  register...), for the exit reason.

Sample k's answer is the position at trigger k; its command acts from trigger k + 1 (the profile's
``input_delay_samples = 1``, modelled in the design).

- Lockstep (:func:`run_host_clocked_lockstep`): trigger, ``drive.service()`` (the embedded drive
  advances one period on the trigger, samples and answers), receive, cycle. Deterministic.
  ``time_ns`` is ``k * period_ns``. A trigger that never reached the drive (lost on the bus) still
  costs it a period (``advance_period``), as a drive on its own crystal would see it.
- Real time (:func:`run_host_clocked_realtime`): absolute deadlines ``t0 + k * period_ns`` on
  ``time.monotonic_ns``; sleep until ``spin_ns`` before each, then spin to it; send the trigger,
  read the answer until ``answer_fraction`` of the period has passed, run the pure step through the
  :class:`~dob_hil.loop.cycle.ControlCycle`, send the command before the next deadline. Lateness
  (trigger send time - deadline) and compute time go into each sample like the drive-clocked
  runner's timing fields. A sample whose deadline has passed by more than a period when the loop
  gets to it, more than half a period late, is not sent: the loop skips ahead (no burst), logs the
  skipped samples as missing (``ControlCycle.on_lost``, an ``overrun_skip`` event: missed
  triggers) and flags the next sample as an overrun. A missing answer follows the missing-feedback
  policy (``feedback_lost`` event when answers resume); ``timeout_periods`` in a row end the run.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from typing import Protocol

from dob_hil.errors import DriveFault
from dob_hil.link.base import DriveLink
from dob_hil.loop.cycle import ControlCycle
from dob_hil.loop.runners import LockstepDrive, LoopLimits, LoopLog, StopRequest

DEFAULT_SPIN_NS = 100_000
DEFAULT_ANSWER_FRACTION = 0.75  # of the period: how long the runner waits for the answer
PROGRESS_EVERY = 4096


class HostClockedLink(DriveLink, Protocol):
    """A :class:`~dob_hil.link.base.DriveLink` whose drive samples when the host triggers it."""

    def send_trigger(self) -> int:
        """Trigger one sample (SYNC, RTR, ...); returns the send time in ns. Raises on a failed send."""

    def drain(self) -> None:
        """Read and judge the frames already queued (non-blocking)."""

    def describe_fault(self, wait_ns: int = 0) -> str:
        """The drive's own account of its fault (read within ``wait_ns``), for the exit reason."""


def _fault(link: HostClockedLink, k: int, wait_ns: int) -> DriveFault:
    return DriveFault(f"the drive reports a fault at sample {k}: {link.describe_fault(wait_ns)}")


def _log_gap(log: LoopLog, time_ns: int, k: int, count: int) -> None:
    log.event(time_ns, "warning", "feedback_lost", f"no answer to {count} trigger(s) before sample {k}",
              {"first_sample": k - count, "count": count})  # fmt: skip


def _period_index_reader(drive: LockstepDrive) -> Callable[[], int]:
    """The drive's ``lockstep_period_index()`` reader where it offers one (no property per sample),
    else a reader of its ``period_index`` property."""
    reader = getattr(drive, "lockstep_period_index", None)
    if reader is not None:
        read: Callable[[], int] = reader()
        return read
    return functools.partial(getattr, drive, "period_index")


def run_host_clocked_lockstep(
    cycle: ControlCycle,
    link: HostClockedLink,
    drive: LockstepDrive,
    log: LoopLog,
    limits: LoopLimits,
    stop: StopRequest,
    progress: Callable[[int], None] | None = None,
) -> str:
    """Run ``limits.n_samples`` triggered samples against the embedded drive; returns the exit reason."""
    period_ns = limits.period_ns
    trigger, service, receive = link.send_trigger, drive.service, link.receive_feedback
    on_feedback, on_missing = cycle.on_feedback, cycle.on_missing
    period_index = _period_index_reader(drive)
    missing_run = 0
    for k in range(limits.n_samples):
        reason = stop.requested
        if reason is not None:
            return reason
        trigger()
        service()
        if period_index() < k:  # the trigger never reached the drive: its time runs on
            drive.advance_period()
        fb = receive(0)
        time_ns = k * period_ns
        if fb is None:
            missing_run += 1
            if missing_run >= limits.timeout_periods:
                raise DriveFault(
                    f"no answer from the drive to {missing_run} triggers in a row (host timeout)"
                )
            on_missing(k, time_ns, k, 0, False)
        else:
            if missing_run:
                _log_gap(log, time.monotonic_ns(), k, missing_run)
                missing_run = 0
            if fb.fault:
                raise _fault(link, k, 0)
            on_feedback(k, time_ns, fb, 0, False)
        if k % PROGRESS_EVERY == 0:
            log.flush()
            if progress is not None:
                progress(k)
    if missing_run:
        _log_gap(log, time.monotonic_ns(), limits.n_samples, missing_run)
    service()  # let the drive take the last command
    return "completed"


def sleep_until(deadline_ns: int, clock_ns: Callable[[], int], spin_ns: int) -> None:
    """Sleep until ``spin_ns`` before ``deadline_ns``, then spin to it."""
    remaining_ns = deadline_ns - clock_ns()
    if remaining_ns > spin_ns:
        time.sleep((remaining_ns - spin_ns) * 1e-9)
    while clock_ns() < deadline_ns:
        pass


def run_host_clocked_realtime(
    cycle: ControlCycle,
    link: HostClockedLink,
    log: LoopLog,
    limits: LoopLimits,
    stop: StopRequest,
    *,
    clock_ns: Callable[[], int] = time.monotonic_ns,
    spin_ns: int = DEFAULT_SPIN_NS,
    answer_fraction: float = DEFAULT_ANSWER_FRACTION,
    lead_periods: int = 2,
    progress: Callable[[int], None] | None = None,
) -> str:
    """Trigger ``limits.n_samples`` samples at absolute deadlines; returns the exit reason."""
    period_ns = limits.period_ns
    answer_ns = int(period_ns * answer_fraction)
    trigger, receive = link.send_trigger, link.receive_feedback
    t0_ns = clock_ns() + lead_periods * period_ns
    missing_run = 0
    overrun = False
    k = 0
    while k < limits.n_samples:
        reason = stop.requested
        if reason is not None:
            return reason
        deadline_ns = t0_ns + k * period_ns
        sleep_until(deadline_ns, clock_ns, spin_ns)
        sent_ns = trigger()
        lateness_ns = sent_ns - deadline_ns
        fb = receive(max(deadline_ns + answer_ns - clock_ns(), 0))
        if fb is None:
            missing_run += 1
            if missing_run >= limits.timeout_periods:
                raise DriveFault(
                    f"no answer from the drive to {missing_run} triggers in a row "
                    f"({missing_run * period_ns / 1e6:g} ms: host timeout)"
                )
            cycle.on_missing(k, deadline_ns, k, lateness_ns, overrun)
        else:
            if missing_run:
                _log_gap(log, clock_ns(), k, missing_run)
                missing_run = 0
            if fb.fault:
                raise _fault(link, k, 20 * period_ns)
            cycle.on_feedback(k, deadline_ns, fb, lateness_ns, overrun)
        log.flush()
        link.drain()
        k += 1
        overrun = False
        late_by_ns = clock_ns() - (t0_ns + k * period_ns)
        if late_by_ns > period_ns // 2 and k < limits.n_samples:
            # more than half a period behind: skip the deadlines already passed, no burst
            skip = min((late_by_ns - period_ns // 2) // period_ns + 1, limits.n_samples - k)
            text = f"{skip} trigger(s) from sample {k} skipped: the loop was {late_by_ns / 1e3:.0f} us late"
            log.event(clock_ns(), "warning", "overrun_skip", text, {"first_sample": k, "count": skip})
            cycle.stats.skipped += skip
            for _ in range(skip):
                cycle.on_lost(k, t0_ns + k * period_ns, k)
                k += 1
            overrun = True
        if progress is not None and k % 3333 == 0:
            progress(k)
    if missing_run:
        _log_gap(log, clock_ns(), limits.n_samples, missing_run)
    return "completed"
