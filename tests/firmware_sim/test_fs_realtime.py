"""The real-time clock: own timer and receive threads; only counts and ordering are asserted."""

from __future__ import annotations

import itertools
import math
import time

import can
import pytest
from fs_support import Host, feedbacks, make_config

from dob_hil.link.protocol import (
    CommandFrame,
    ControlFrame,
    ControlRequest,
    DriveState,
    FaultCode,
    FaultFrame,
    FeedbackFrame,
    FrameKind,
    HeartbeatFrame,
    Status,
    encode_command,
    encode_control,
)
from firmware_sim import GroundTruth, SimulatedDrive
from firmware_sim.core import FIRST_COMMAND_TIMEOUT_NS, DriveCore, FrameResult

PERIOD_US = 1000.0
PLANT = {"period_us": PERIOD_US}
NO_DIST = {"disturbance": None}


PATIENCE_S = 60.0  # a bound against a hang only: a loaded machine may starve the drive's threads


def collect(host: Host, n_feedback: int, timeout_s: float = PATIENCE_S) -> list[object]:
    """Frames until ``n_feedback`` feedbacks arrived (or ``timeout_s``, a bound against a hang):
    counts, not wall time, so that a starved machine only makes it slower."""
    frames: list[object] = []
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and len(feedbacks(frames)) < n_feedback:  # type: ignore[arg-type]
        frames.extend(host.drain(0.01))
    return frames


def seq_steps(fbs: list[FeedbackFrame]) -> list[int]:
    return [(b.seq - a.seq) % 256 for a, b in itertools.pairwise(fbs)]


def test_feedback_every_period_in_order(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, drive_bus = bus_pair
    host = Host(host_bus)
    truth: list[GroundTruth] = []
    cfg = make_config(plant=PLANT, sim=NO_DIST)
    with SimulatedDrive(drive_bus, cfg, clock="realtime", truth_sink=truth.append) as drive:
        assert drive.running
        frames = collect(host, 50)
        drive.check()
    fbs = feedbacks(frames)  # type: ignore[arg-type]
    stats = drive.stats
    assert len(fbs) >= 50
    assert fbs[0].seq == 0 and fbs[0].status == Status(0)
    steps = seq_steps(fbs)
    assert all(s >= 1 for s in steps)
    assert sum(s - 1 for s in steps) <= stats.overruns  # gaps only where the timer skipped ahead
    assert stats.feedback_sent >= len(fbs) and stats.feedback_lost == 0
    assert [t.period_index for t in truth] == sorted({t.period_index for t in truth})
    assert all(t.time_ns == t.period_index * 1_000_000 for t in truth)
    assert not drive.running  # stopped by the with block


def test_host_loop_enables_and_commands_in_real_time(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, drive_bus = bus_pair
    host = Host(host_bus)
    truth: list[GroundTruth] = []
    # a watchdog of 60 s (60000 periods): a starved test process must not trip it
    cfg = make_config(plant=PLANT, sim=NO_DIST, drive={"watchdog_periods": 60_000})
    with SimulatedDrive(drive_bus, cfg, clock="realtime", truth_sink=truth.append) as drive:
        host.control(ControlRequest.ENABLE)
        host.wait_for(HeartbeatFrame)
        answered = 0
        end = time.monotonic() + PATIENCE_S  # a bound against a hang only; counts end the loop
        while time.monotonic() < end and drive.stats.commands_accepted < 20:
            newest = None
            for f in host.drain(0.01):
                if isinstance(f, FeedbackFrame) and f.status & Status.ENABLED:
                    newest = f
            if newest is not None:  # answer the newest only, as the host loop does
                host.command(1024, newest.seq)  # 0.5 A
                answered += 1
        deadline = time.monotonic() + PATIENCE_S
        judged = lambda: drive.stats.commands_accepted + drive.stats.commands_stale  # noqa: E731
        while judged() < answered and time.monotonic() < deadline:
            time.sleep(0.01)  # the last command may still be on its way to the drive
        assert drive.state is DriveState.ENABLED
        stats = drive.stats
    assert stats.commands_accepted >= 20
    # the virtual bus loses nothing: every command reached the drive and was accepted or judged stale
    assert stats.commands_accepted + stats.commands_stale == answered
    applied = [t.applied_current_A for t in truth]
    assert 0.5 in applied
    assert set(applied) <= {0.0, 0.5}
    # the plant moved forward under the positive current
    assert truth[-1].state[0] > 0.0 and truth[-1].state[1] > 0.0


def test_watchdog_trips_once_armed_by_a_first_command(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    """50 periods of watchdog (so 50 ms to answer a feedback: a loaded machine once took more than
    the 5 ms of a 5-period watchdog, the answer was stale and the unarmed watchdog tripped with
    info 0). The host answers the newest ENABLED feedback until the drive accepts one, then falls
    silent: the trip's info is the 50 periods missed."""
    host_bus, drive_bus = bus_pair
    host = Host(host_bus)
    with SimulatedDrive(
        drive_bus, make_config(plant=PLANT, drive={"watchdog_periods": 50}), clock="realtime"
    ) as drive:
        host.control(ControlRequest.ENABLE)
        frames = host.wait_for(HeartbeatFrame, timeout_s=PATIENCE_S)
        deadline = time.monotonic() + PATIENCE_S
        while drive.stats.commands_accepted == 0 and drive.state is not DriveState.FAULT:
            assert time.monotonic() < deadline, "no command accepted"
            fb = host.wait_for(FeedbackFrame)[-1]
            assert isinstance(fb, FeedbackFrame)
            if fb.status & Status.ENABLED:
                judged = drive.stats.commands_accepted + drive.stats.commands_stale
                host.command(0, fb.seq)
                while drive.stats.commands_accepted + drive.stats.commands_stale == judged:
                    assert time.monotonic() < deadline, "the command was never judged"
                    time.sleep(0.001)
        assert drive.stats.commands_accepted == 1
        frames = host.wait_for(FaultFrame, timeout_s=PATIENCE_S)
        frames += host.wait_for(FeedbackFrame)
        assert drive.state is DriveState.FAULT
    assert FaultFrame(FaultCode.WATCHDOG, 50) in frames
    assert feedbacks(frames)[-1].status == Status.FAULT | Status.WATCHDOG  # type: ignore[arg-type]


def test_watchdog_without_a_first_command_trips_with_info_0(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    """Not armed, the watchdog allows the host FIRST_COMMAND_TIMEOUT_NS (not watchdog_periods)."""
    host_bus, drive_bus = bus_pair
    host = Host(host_bus)
    with SimulatedDrive(
        drive_bus, make_config(plant=PLANT, drive={"watchdog_periods": 5}), clock="realtime"
    ) as drive:
        host.control(ControlRequest.ENABLE)
        frames = host.wait_for(FaultFrame, timeout_s=10.0)
        assert drive.state is DriveState.FAULT
        periods = drive.stats.samples
    assert FaultFrame(FaultCode.WATCHDOG, 0) in frames
    assert periods * PLANT["period_us"] * 1000 >= FIRST_COMMAND_TIMEOUT_NS  # type: ignore[operator]


def test_loss_latency_and_jitter_keep_order(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, drive_bus = bus_pair
    host = Host(host_bus)
    sim = {"disturbance": None, "loss_probability": 0.3, "latency_us": 1500.0, "jitter_us": 800.0, "seed": 1}
    with SimulatedDrive(drive_bus, make_config(plant=PLANT, sim=sim), clock="realtime") as drive:
        frames = collect(host, 40)
    fbs = feedbacks(frames)  # type: ignore[arg-type]
    stats = drive.stats
    assert stats.feedback_lost > 0 and len(fbs) >= 40
    assert all(s >= 1 for s in seq_steps(fbs))  # never reordered
    assert sum(s - 1 for s in seq_steps(fbs)) > 0  # lost frames leave gaps


def test_a_thread_exception_surfaces_in_check_and_stop(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    calls = []

    def bad_sink(truth: GroundTruth) -> None:
        calls.append(truth)
        if len(calls) == 3:
            raise RuntimeError("sink broke")

    drive = SimulatedDrive(bus_pair[1], make_config(plant=PLANT), clock="realtime", truth_sink=bad_sink)
    drive.start()
    deadline = time.monotonic() + PATIENCE_S
    while len(calls) < 3 and time.monotonic() < deadline:
        time.sleep(0.005)
    time.sleep(0.02)
    with pytest.raises(RuntimeError, match="sink broke"):
        drive.check()
    with pytest.raises(RuntimeError, match="sink broke"):
        drive.stop()
    assert len(calls) == 3  # the timer thread stopped on the error


def test_start_twice_is_refused_and_stop_twice_is_fine(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    drive = SimulatedDrive(bus_pair[1], make_config(plant=PLANT), clock="realtime")
    drive.start()
    with pytest.raises(RuntimeError, match="already started"):
        drive.start()
    drive.stop()
    drive.stop()
    drive.close()


# --- the real-time mechanism without threads: a command acts from its arrival instant ----------------
def test_command_takes_effect_at_its_arrival_instant() -> None:
    cfg = make_config(sim=NO_DIST)
    core = DriveCore(cfg, accept_window=10, want_truth=True)
    cmd_id, ctl_id = core.command_id, core.control_id
    core.on_frame(ctl_id, encode_control(ControlFrame(ControlRequest.ENABLE)), 0)
    core.sample()
    arrival_ns = 123_000  # inside the first period, in its 5th sub-step
    core.integrate_to(arrival_ns - 50_000)  # the timer may have integrated part of the way
    assert (
        core.on_frame(cmd_id, encode_command(CommandFrame(1024, 0, True)), arrival_ns) is FrameResult.COMMAND
    )
    core.integrate_to(300_000)
    a, b, u, t = 128.59, 2.1484e4, 0.5, (300_000 - arrival_ns) * 1e-9
    x = b * u / a * (t - (1 - math.exp(-a * t)) / a)
    v = b * u / a * (1 - math.exp(-a * t))
    assert core.plant.state == pytest.approx((x, v), rel=1e-9)
    _, truth = core.sample()
    assert truth is not None and truth.applied_current_A == 0.5


def test_realtime_window_accepts_a_late_command_once() -> None:
    core = DriveCore(make_config(sim=NO_DIST), accept_window=10, want_truth=False)
    core.on_frame(core.control_id, encode_control(ControlFrame(ControlRequest.ENABLE)), 0)
    for _ in range(3):
        core.sample()  # samples 0, 1, 2
    late = encode_command(CommandFrame(100, 1, True))
    assert core.on_frame(core.command_id, late, 0) is FrameResult.COMMAND  # answers sample 1: late, fine
    assert core.on_frame(core.command_id, late, 0) is FrameResult.STALE_COMMAND  # duplicate
    older = encode_command(CommandFrame(100, 0, True))
    assert core.on_frame(core.command_id, older, 0) is FrameResult.STALE_COMMAND  # older than accepted
    assert (
        core.on_frame(core.command_id, encode_command(CommandFrame(100, 2, True)), 0) is FrameResult.COMMAND
    )
    assert core.on_frame(FrameKind.COMMAND + 9, late, 0) is FrameResult.IGNORED
