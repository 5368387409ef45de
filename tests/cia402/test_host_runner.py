"""The host-clocked real-time runner on a simulated clock: triggers at absolute deadlines, lateness
and missed triggers accounted, overruns skipped ahead (no burst), missing answers and host timeout,
a drive fault named with the drive's own account. Profile-neutral: a fake HostClockedLink."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import pytest

from dob_hil.errors import DriveFault
from dob_hil.link.base import Feedback
from dob_hil.loop.cycle import CycleStats
from dob_hil.loop.host_clocked import run_host_clocked_lockstep, run_host_clocked_realtime
from dob_hil.loop.runners import LoopLimits

PERIOD_NS = 1_000_000


class Clock:
    """Simulated monotonic time: every read moves it 1 us on (so a spin loop ends)."""

    def __init__(self) -> None:
        self.now_ns = 0

    def __call__(self) -> int:
        self.now_ns += 1_000
        return self.now_ns


@dataclass
class FakeLink:
    clock: Clock
    answer: Any = True  # callable(k) -> bool: whether trigger k is answered
    fault_at: int | None = None
    triggers: list[int] = field(default_factory=list)

    def send_trigger(self) -> int:
        self.triggers.append(self.clock.now_ns)
        return self.clock()

    def receive_feedback(self, timeout_ns: int) -> Feedback | None:
        k = len(self.triggers) - 1
        if callable(self.answer) and not self.answer(k):
            self.clock.now_ns += timeout_ns
            return None
        fault = self.fault_at is not None and k >= self.fault_at
        return Feedback(self.clock(), k & 0xFF, (k,), (k,), (k / 1e4,), not fault, fault, False)

    def drain(self) -> None:
        pass

    def describe_fault(self, wait_ns: int = 0) -> str:
        return "node 1: FAULT (statusword 0x0008), EMCY 0x2310 (continuous over current), register 0x03"


@dataclass
class FakeCycle:
    clock: Clock
    slow: dict[int, int] = field(default_factory=dict)  # sample -> compute ns
    calls: list[tuple[str, int, int, bool]] = field(default_factory=list)  # (kind, k, lateness, overrun)
    stats: CycleStats = field(default_factory=CycleStats)

    def on_feedback(self, k: int, time_ns: int, fb: Feedback, lateness_ns: int, overrun: bool) -> None:
        self.clock.now_ns += self.slow.get(k, 50_000)
        self.calls.append(("fb", k, lateness_ns, overrun))

    def on_missing(self, k: int, time_ns: int, answers_seq: int, lateness_ns: int, overrun: bool) -> None:
        self.calls.append(("missing", k, lateness_ns, overrun))

    def on_lost(self, k: int, time_ns: int, feedback_seq: int) -> None:
        self.calls.append(("lost", k, 0, False))


class FakeLog:
    def __init__(self) -> None:
        self.events: list[tuple[str, str, dict[str, int] | None]] = []

    def event(
        self, time_ns: int, level: str, kind: str, message: str, data: dict[str, int] | None = None
    ) -> None:
        self.events.append((kind, message, data))

    def flush(self) -> None:
        pass


class NoStop:
    requested: str | None = None


def _run(n: int, link: FakeLink, cycle: FakeCycle, log: FakeLog, timeout_periods: int = 5) -> str:
    return run_host_clocked_realtime(
        cycle,  # type: ignore[arg-type]
        link,  # type: ignore[arg-type]
        log,  # type: ignore[arg-type]
        LoopLimits(n, PERIOD_NS, timeout_periods),
        NoStop(),
        clock_ns=link.clock,
        spin_ns=0,
    )


def test_triggers_at_absolute_deadlines_and_an_overrun_skips_ahead() -> None:
    clock = Clock()
    link, cycle, log = FakeLink(clock), FakeCycle(clock, slow={5: 2_600_000}), FakeLog()
    assert _run(20, link, cycle, log) == "completed"
    kinds = [(c[0], c[1]) for c in cycle.calls]
    assert [k for _, k in kinds] == list(range(20))  # every sample accounted, in order
    assert kinds[6:8] == [("lost", 6), ("lost", 7)]  # 2.6 ms of compute: deadlines 6 and 7 passed
    assert cycle.calls[8][3] is True and sum(c[3] for c in cycle.calls) == 1  # sample 8 flagged overrun
    t0 = link.triggers[0]
    assert [t - t0 for t in link.triggers] == [k * PERIOD_NS for k in range(20) if k not in (6, 7)]
    assert cycle.stats.skipped == 2
    assert [(e[0], e[2]) for e in log.events] == [("overrun_skip", {"first_sample": 6, "count": 2})]
    assert all(0 < c[2] < 10_000 for c in cycle.calls if c[0] == "fb")  # lateness: the send, measured


def test_a_small_lateness_is_not_a_skip() -> None:
    clock = Clock()
    link, cycle, log = FakeLink(clock), FakeCycle(clock, slow={3: 1_200_000}), FakeLog()
    _run(8, link, cycle, log)
    assert [c[0] for c in cycle.calls] == ["fb"] * 8 and not log.events
    assert cycle.calls[4][2] > 100_000  # sample 4's trigger went out late, and that is logged


def test_missing_answers_follow_the_policy_and_a_gap_is_logged() -> None:
    clock = Clock()
    link = FakeLink(clock, answer=lambda k: k not in (3, 4, 9))
    cycle, log = FakeCycle(clock), FakeLog()
    assert _run(10, link, cycle, log) == "completed"
    assert [c[1] for c in cycle.calls if c[0] == "missing"] == [3, 4, 9]
    gaps = [e[2] for e in log.events if e[0] == "feedback_lost"]
    assert gaps == [{"first_sample": 3, "count": 2}, {"first_sample": 9, "count": 1}]  # the last at the end


def test_no_answers_end_the_run_by_host_timeout() -> None:
    clock = Clock()
    link = FakeLink(clock, answer=lambda k: k < 4)
    with pytest.raises(DriveFault, match="no answer from the drive to 5 triggers"):
        _run(50, link, FakeCycle(clock), FakeLog())


def test_a_drive_fault_ends_the_run_with_the_drives_account() -> None:
    clock = Clock()
    link = FakeLink(clock, fault_at=7)
    with pytest.raises(DriveFault, match=r"sample 7: .*EMCY 0x2310"):
        _run(50, link, FakeCycle(clock), FakeLog())


class FakeDrive:
    def __init__(self, link: FakeLink, lost: set[int]) -> None:
        self.link, self.lost, self.period_index, self.advanced = link, lost, -1, 0

    def service(self) -> int:
        k = len(self.link.triggers) - 1
        if k in self.lost or k <= self.period_index:
            return 0
        self.period_index = k
        return 1

    def advance_period(self) -> None:
        self.period_index += 1
        self.advanced += 1


def test_lockstep_a_lost_trigger_still_costs_the_drive_a_period() -> None:
    clock = Clock()
    link = FakeLink(clock, answer=lambda k: k != 4)
    drive, cycle, log = FakeDrive(link, {4}), FakeCycle(clock), FakeLog()
    reason = run_host_clocked_lockstep(
        cycle,
        link,
        drive,
        log,
        LoopLimits(10, PERIOD_NS, 5),
        NoStop(),  # type: ignore[arg-type]
    )
    assert reason == "completed"
    assert drive.advanced == 1 and drive.period_index == 9
    assert [c[0] for c in cycle.calls].count("missing") == 1
    assert [e[2] for e in log.events] == [{"first_sample": 4, "count": 1}]
