"""DriveCore.lockstep_period (the lockstep per-period path in one call) has the same effects as
the general path it replaces: on_frame + integrate_to + period_boundary(True)."""

from __future__ import annotations

import dataclasses
import random
from collections import deque
from collections.abc import Callable, Iterator
from typing import Any

import can
import pytest
from fs_support import make_config

from dob_hil.link.protocol import CommandFrame, ControlFrame, ControlRequest, encode_command, encode_control
from dob_hil.loop.inproc_bus import InProcessBus
from firmware_sim import SimulatedDrive
from firmware_sim.clocked import ClockedDrive
from firmware_sim.core import DriveCore, FrameResult
from firmware_sim.lockstep import LockstepClock

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


def test_the_lockstep_time_source_is_the_core_or_the_drive() -> None:
    drive = _BareDrive()
    assert drive.lockstep_time_source() is drive  # no core: the drive's own time_ns
    drive.time_ns = 5678
    assert drive.lockstep_time_source().time_ns == 5678
    assert drive.service() == 0  # bound straight to the clock's
    bus = InProcessBus("t", deque(), deque())
    try:
        native = SimulatedDrive(bus, make_config(), clock="lockstep")
        source = native.lockstep_time_source()
        assert source is not native  # the core: an attribute, not the drive's property chain
        native.advance_period()
        assert source.time_ns == native.time_ns == native.config.plant.period_ns
    finally:
        bus.shutdown()


ClockPair = tuple[list[Any], list[tuple[LockstepClock, deque[Any], deque[Any]]]]


@pytest.fixture
def clock_pair() -> Iterator[Callable[..., ClockPair]]:
    """Two lockstep clocks on the same config, the first fused (as shipped), the second not; each
    with its in-process bus (to the drive, from the drive), shut down after the test. Their truth
    goes to one list each."""
    buses: list[InProcessBus] = []

    def make(input_delay_samples: int = 0, **sections: dict[str, Any]) -> ClockPair:
        cfg = make_config(**sections)
        if input_delay_samples:  # the drive's side only (the design would need the delay states)
            plant = dataclasses.replace(cfg.plant, input_delay_samples=input_delay_samples)
            cfg = dataclasses.replace(cfg, plant=plant)
        truths: list[Any] = [[], []]
        clocks = []
        for i in range(2):
            to_drive: deque[Any] = deque()
            from_drive: deque[Any] = deque()
            bus = InProcessBus("t", to_drive, from_drive)
            buses.append(bus)
            clock = LockstepClock(bus, cfg, truths[i].append)
            clock.fused = i == 0
            clocks.append((clock, to_drive, from_drive))
        return truths, clocks

    yield make
    for bus in buses:
        bus.shutdown()


def _frames(q: deque[Any]) -> list[tuple[int, bytes]]:
    out = [(m.arbitration_id, bytes(m.data)) for m in q]
    q.clear()
    return out


@pytest.mark.parametrize(
    "sections",
    [
        {"sim": {"noise_counts_std": 1.5, "seed": 3, "loss_probability": 0.05}},
        {"sim": {"disturbance": []}},  # no disturbance: the other cell loop
        {"input_delay_samples": 1},  # declined every period
    ],
    ids=["noise-loss-disturbance", "no-disturbance", "input-delay"],
)
def test_exchange_matches_the_general_path(
    sections: dict[str, Any], clock_pair: Callable[..., ClockPair]
) -> None:
    """LockstepClock._exchange (command, period, sample, FEEDBACK, truth in one call) sends the
    same frames, hands on the same truth and leaves the same state as the general path, over
    saturated, stale and stopping commands and the heartbeat periods."""
    truths, clocks = clock_pair(**sections)
    enable = encode_control(ControlFrame(ControlRequest.ENABLE))
    for clock, to_drive, _ in clocks:
        to_drive.append(can.Message(arbitration_id=clock.core.control_id, data=enable, is_extended_id=False))
        clock.service()
    rng = random.Random(9)
    seq = 0
    fused_periods = 0
    for _ in range(PERIODS):
        sent = [_frames(from_drive) for _, _, from_drive in clocks]
        assert sent[0] == sent[1]
        fb = [p for aid, p in sent[0] if aid == clocks[0][0]._feedback_id]
        if fb:
            seq = fb[-1][4]
        answer = seq if rng.random() > 0.02 else (seq + 9) % 256  # a few stale answers
        enable_bit = rng.random() > 0.01  # a few stops
        counts = rng.randint(-3000, 3000)  # beyond the limit at times: saturated
        payload = encode_command(CommandFrame(counts, answer & 0x7F, enable_bit))
        before = clocks[0][0].core.stats.samples
        for clock, to_drive, _ in clocks:
            cmd = clock.core.command_id
            to_drive.append(can.Message(arbitration_id=cmd, data=payload, is_extended_id=False))
            clock.service()
        a, b = clocks[0][0].core, clocks[1][0].core
        if a.stats.samples == before:  # the command did not advance the period: advance it
            for clock, _, _ in clocks:
                clock.advance_period()
        else:
            fused_periods += 1
        assert a.time_ns == b.time_ns
        assert a.plant.state == b.plant.state
        assert (a.saturated, a._last_accepted, a.path.held_A) == (
            b.saturated,
            b._last_accepted,
            b.path.held_A,
        )
        assert vars(a.stats) == vars(b.stats)
        assert (a.watchdog.armed, a.watchdog.missed) == (b.watchdog.armed, b.watchdog.missed)
        assert a.state is b.state
    assert truths[0] == truths[1]
    assert len(truths[0]) > PERIODS * 0.9
    assert fused_periods > PERIODS * 0.5
    if "input_delay_samples" not in sections:
        assert clocks[0][0].core.stats.commands_accepted > PERIODS * 0.9


def test_exchange_declines_without_changing_anything(clock_pair: Callable[..., ClockPair]) -> None:
    """A declined _exchange leaves the core untouched (the caller then takes the general path)."""
    truths, clocks = clock_pair()
    clock = clocks[0][0]
    before = (clock.core.time_ns, clock.core.plant.state, vars(clock.core.stats).copy())
    assert not clock._exchange(100, 0)  # not ENABLED (and no sample yet)
    assert (clock.core.time_ns, clock.core.plant.state, vars(clock.core.stats)) == before
    assert not truths[0] and not clocks[0][2]


def test_lockstep_readers_refuse_a_real_time_drive_naming_the_call() -> None:
    bus = InProcessBus("t", deque(), deque())
    try:
        drive = SimulatedDrive(bus, make_config(), clock="realtime")
        for name in ("lockstep_time_source", "service", "advance_period"):
            with pytest.raises(RuntimeError, match=rf"^{name}\(\) is for the lockstep clock"):
                getattr(drive, name)()
    finally:
        bus.shutdown()
