"""The two schedules of the loop: lockstep (with the embedded simulated drive) and real time.

Both call the same :class:`~dob_hil.loop.cycle.ControlCycle`; they differ only in how a sample
instant comes about.

- Lockstep: the embedded drive advances one period per command; ``drive.service()`` runs between
  the command and the next receive, in this thread. Deterministic, as fast as the CPU allows.
  ``time_ns`` is the simulated sample instant ``k * period_ns``.
- Real time: the drive is the clock (it sends feedback every period). The host expects sample k
  at the absolute instant ``anchor + k * period_ns``, where the anchor follows the drive's clock
  with a slow first-order tracker (64 samples) so that drift between the two clocks does not
  accumulate. A feedback that has not arrived half a period after its instant is *missing* (the
  cycle substitutes per the policy and still answers, so the drive's watchdog stays fed). A
  feedback read a full period late or more is an *overrun*: the runner drains what is queued and
  continues with the newest feedback (skips ahead) rather than answering a burst of stale ones;
  every skipped sample is counted and reported as an event.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from dob_hil.errors import DriveFault
from dob_hil.link.base import DriveLink
from dob_hil.log import LogWriter
from dob_hil.loop.cycle import ControlCycle

SEQ_MODULO = 256


class StopRequest(Protocol):
    @property
    def requested(self) -> str | None: ...


class LockstepDrive(Protocol):
    def service(self) -> int: ...


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
    log: LogWriter,
    limits: LoopLimits,
    stop: StopRequest,
    progress: Callable[[int], None] | None = None,
) -> str:
    """Run ``limits.n_samples`` samples; returns the exit reason ("completed" or the stop reason)."""
    period_ns = limits.period_ns
    expected_seq: int | None = None
    missing_run = 0
    on_feedback, on_missing, receive, service = cycle.on_feedback, cycle.on_missing, link.receive_feedback, drive.service
    flush = log.flush
    progress_every = 4096
    for k in range(limits.n_samples):
        reason = stop.requested
        if reason is not None:
            return reason
        service()
        fb = receive(0)
        time_ns = k * period_ns
        if fb is None:
            missing_run += 1
            if missing_run >= limits.timeout_periods:
                raise DriveFault(f"no feedback from the drive for {missing_run} periods (host timeout)")
            answer = 0 if expected_seq is None else expected_seq
            on_missing(k, time_ns, answer, 0, False)
        else:
            missing_run = 0
            if fb.fault:
                raise DriveFault(f"the drive reports a fault (feedback seq {fb.seq})")
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


def run_realtime(
    cycle: ControlCycle,
    link: DriveLink,
    log: LogWriter,
    limits: LoopLimits,
    stop: StopRequest,
    first_feedback_timeout_ns: int = 2_000_000_000,
    clock_ns: Callable[[], int] = time.monotonic_ns,
    progress: Callable[[int], None] | None = None,
) -> str:
    """Answer the drive's feedback in real time for ``limits.n_samples`` periods."""
    period_ns = limits.period_ns
    half_period_ns = period_ns // 2
    receive = link.receive_feedback
    fb = receive(first_feedback_timeout_ns)
    if fb is None:
        raise DriveFault(f"no feedback from the drive within {first_feedback_timeout_ns / 1e9:g} s of enabling")
    anchor_ns = fb.rx_time_ns
    expected_seq = fb.seq
    missing_run = 0
    skipped_total = 0
    k = 0
    while k < limits.n_samples:
        reason = stop.requested
        if reason is not None:
            return reason
        instant_ns = anchor_ns + k * period_ns
        if fb is None:
            wait_ns = instant_ns + half_period_ns - clock_ns()
            fb = receive(wait_ns if wait_ns > 0 else 0)
        if fb is None:
            missing_run += 1
            if missing_run >= limits.timeout_periods:
                raise DriveFault(f"no feedback from the drive for {missing_run} periods (host timeout)")
            now = clock_ns()
            cycle.on_missing(k, instant_ns, expected_seq, now - instant_ns, now - instant_ns >= period_ns)
            log.event(now, "warning", "feedback_missing", f"no feedback for sample {k} (seq {expected_seq})")
            k += 1
            expected_seq = (expected_seq + 1) % SEQ_MODULO
            log.flush()
            continue
        if fb.fault:
            raise DriveFault(f"the drive reports a fault (feedback seq {fb.seq})")
        missing_run = 0
        delta = _seq_delta(fb.seq, expected_seq)
        if delta < 0:  # older than expected: already answered or substituted
            log.event(clock_ns(), "warning", "stale_feedback", f"feedback seq {fb.seq} is {-delta} behind")
            fb = None
            continue
        if delta > 0:  # the drive's frames for `delta` samples never reached us
            log.event(
                clock_ns(),
                "warning",
                "feedback_lost",
                f"{delta} feedback frame(s) lost before seq {fb.seq} (samples {k}..{k + delta - 1})",
                {"first_sample": k, "count": delta},
            )
            skipped_total += delta
            k += delta
            if k >= limits.n_samples:
                break
            instant_ns = anchor_ns + k * period_ns
        lateness_ns = fb.rx_time_ns - instant_ns
        overrun = lateness_ns >= period_ns
        if overrun:
            # Skip ahead: answer only the newest feedback already queued, not a burst of stale ones.
            newest = fb
            drained = 0
            while (nxt := receive(0)) is not None:
                newest, drained = nxt, drained + 1
            if drained:
                ahead = _seq_delta(newest.seq, fb.seq)
                log.event(
                    clock_ns(),
                    "warning",
                    "overrun_skip",
                    f"read sample {k} {lateness_ns / 1000:.0f} us late; skipped {ahead} sample(s)",
                    {"first_sample": k, "count": ahead, "lateness_ns": lateness_ns},
                )
                skipped_total += ahead
                k += ahead
                fb = newest
                expected_seq = newest.seq
                if k >= limits.n_samples:
                    break
                instant_ns = anchor_ns + k * period_ns
                lateness_ns = fb.rx_time_ns - instant_ns
        elif -period_ns < lateness_ns:
            anchor_ns += lateness_ns >> 6  # track the drive's clock (first order, 64 samples)
        cycle.on_feedback(k, instant_ns, fb, lateness_ns, overrun)
        log.flush()
        k += 1
        expected_seq = (fb.seq + 1) % SEQ_MODULO
        fb = None
        if progress is not None and k % 3333 == 0:
            progress(k)
    cycle.stats.skipped = skipped_total
    return "completed"
