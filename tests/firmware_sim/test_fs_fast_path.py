"""DriveCore.lockstep_period (the lockstep per-period path in one call) has the same effects as
the general path it replaces: on_frame + integrate_to + period_boundary(True)."""

from __future__ import annotations

import random
from collections import deque
from typing import Any

from fs_support import make_config

from dob_hil.link.protocol import CommandFrame, ControlFrame, ControlRequest, encode_command, encode_control
from dob_hil.loop.inproc_bus import InProcessBus
from firmware_sim import SimulatedDrive
from firmware_sim.clocked import ClockedDrive
from firmware_sim.core import DriveCore, FrameResult

PERIODS = 1500  # past 100 ms: heartbeats fall due on the way (the fast path declines those periods)


def _enabled_pair() -> tuple[DriveCore, DriveCore]:
    cfg = make_config(sim={"noise_counts_std": 1.5, "seed": 3})
    cores = (
        DriveCore(cfg, accept_window=1, want_truth=True),
        DriveCore(cfg, accept_window=1, want_truth=True),
    )
    for core in cores:
        core.on_frame(core.control_id, encode_control(ControlFrame(ControlRequest.ENABLE)), 0)
        core.take_outgoing()
        core.sample()
    return cores[0], cores[1]


def test_lockstep_period_matches_the_general_path() -> None:
    general, fast = _enabled_pair()
    rng = random.Random(5)
    declined = 0
    for _ in range(PERIODS):
        last = general.last_seq
        assert last is not None and last == fast.last_seq
        seq = last if rng.random() > 0.02 else (last + 7) % 256  # a few stale answers
        counts = rng.randint(-3000, 3000)  # beyond the limit at times: saturated
        payload = encode_command(CommandFrame(counts, seq & 0x7F, True))
        result = general.on_frame(general.command_id, payload, general.time_ns)
        if result is FrameResult.COMMAND:
            general.integrate_to(general.time_ns + general.period_ns)
            general.period_boundary(True)
        if not fast.lockstep_period(counts, seq & 0x7F):
            declined += 1
            if fast.on_frame(fast.command_id, payload, fast.time_ns) is FrameResult.COMMAND:
                fast.integrate_to(fast.time_ns + fast.period_ns)
                fast.period_boundary(True)
        assert fast.time_ns == general.time_ns
        assert fast.take_outgoing() == general.take_outgoing()
        if result is FrameResult.COMMAND:
            assert fast.sample() == general.sample()
        assert fast.plant.state == general.plant.state
        assert fast.saturated == general.saturated
        assert vars(fast.stats) == vars(general.stats)
        assert (fast.watchdog.armed, fast.watchdog.missed) == (
            general.watchdog.armed,
            general.watchdog.missed,
        )
    assert 0 < declined < PERIODS // 4  # stale answers and heartbeat periods took the general path


def test_lockstep_period_declines_without_changing_anything() -> None:
    _, fast = _enabled_pair()
    before = (fast.time_ns, fast.plant.state, vars(fast.stats).copy(), fast._last_accepted)
    assert not fast.lockstep_period(100, 5)  # answers no recent sample: stale
    fast.on_frame(fast.control_id, encode_control(ControlFrame(ControlRequest.DISABLE)), 0)
    fast.take_outgoing()
    assert not fast.lockstep_period(100, 0)  # not ENABLED
    assert (fast.time_ns, fast.plant.state, fast._last_accepted) == before[:2] + before[3:]
    assert fast.stats.commands_accepted == before[2]["commands_accepted"]


class _BareClock:
    """A lockstep clock without a ``core`` (a drive of another shape)."""

    def service(self) -> int:
        return 0

    def advance_period(self) -> None:
        pass


class _BareDrive(ClockedDrive[_BareClock, Any]):
    def __init__(self) -> None:
        self._lockstep = _BareClock()
        self.time_ns = 1234


def test_lockstep_clock_ns_reads_the_core_or_the_drive() -> None:
    drive = _BareDrive()
    assert drive.lockstep_clock_ns()() == 1234
    drive.time_ns = 5678
    assert drive.lockstep_clock_ns()() == 5678
    assert drive.service() == 0  # bound straight to the clock's
    bus = InProcessBus("t", deque(), deque())
    try:
        native = SimulatedDrive(bus, make_config(), clock="lockstep")
        clock_ns = native.lockstep_clock_ns()
        native.advance_period()
        assert clock_ns() == native.time_ns == native.config.plant.period_ns
    finally:
        bus.shutdown()
