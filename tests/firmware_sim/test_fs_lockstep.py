"""The lockstep clock over a virtual bus, driven by a tiny scripted host using the protocol codec."""

from __future__ import annotations

import math
import statistics

import can
import pytest
from fs_support import Host, feedbacks, make_config

from dob_hil.config import Config
from dob_hil.link.protocol import (
    ControlRequest,
    DriveState,
    FaultCode,
    FaultFrame,
    FeedbackFrame,
    FrameKind,
    HeartbeatFrame,
    Status,
)
from firmware_sim import GroundTruth, SimulatedDrive

NO_DIST = {"disturbance": None}
LSB = 1.0 / 2048.0


class Rig:
    def __init__(self, bus_pair: tuple[can.BusABC, can.BusABC], config: Config) -> None:
        host_bus, drive_bus = bus_pair
        self.truth: list[GroundTruth] = []
        self.host = Host(host_bus, config.drive.node_id)
        self.drive = SimulatedDrive(drive_bus, config, truth_sink=self.truth.append)
        self.config = config

    def enable(self) -> FeedbackFrame:
        self.host.control(ControlRequest.ENABLE)
        assert self.drive.service() == 1
        frames = self.host.drain()
        assert frames[0] == HeartbeatFrame(DriveState.ENABLED)
        fb = feedbacks(frames)
        assert len(fb) == 1
        return fb[0]

    def step(self, counts: int, fb: FeedbackFrame, enable: bool = True) -> FeedbackFrame:
        self.host.command(counts, fb.seq, enable)
        self.drive.service()
        fbs = feedbacks(self.host.drain())
        assert len(fbs) == 1
        return fbs[0]


def test_enable_sends_heartbeat_and_feedback_seq0_at_t0(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    rig = Rig(bus_pair, make_config(sim=NO_DIST))
    assert rig.drive.state is DriveState.DISABLED
    assert rig.drive.service() == 0
    fb = rig.enable()
    assert fb == FeedbackFrame(0, 0, Status.ENABLED)
    assert rig.drive.state is DriveState.ENABLED and rig.drive.period_index == 0
    assert rig.truth == [GroundTruth(0, 0, (0.0, 0.0), 0.0, 0.0, DriveState.ENABLED)]


def test_commands_advance_one_period_each_and_match_the_physics(
    bus_pair: tuple[can.BusABC, can.BusABC],
) -> None:
    rig = Rig(bus_pair, make_config(sim=NO_DIST))
    fb = rig.enable()
    for k in range(1, 301):
        fb = rig.step(512, fb)  # 0.25 A
        assert fb.seq == k % 256
        assert fb.status == Status.ENABLED
        t = rig.truth[-1]
        assert t.period_index == k and t.time_ns == k * 300_000
        assert fb.counts == math.floor(t.state[0] * 10000 + 0.5)
        assert t.applied_current_A == 0.25
    a, b, t_s, u = 128.59, 2.1484e4, 300 * 300e-6, 0.25
    x = b * u / a * (t_s - (1 - math.exp(-a * t_s)) / a)
    assert rig.drive.true_state[0] == pytest.approx(x, rel=1e-10)
    assert rig.drive.stats.commands_accepted == 300 and rig.drive.stats.feedback_sent == 301


def test_saturation_clamps_at_1433_and_sets_the_status_bit(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    rig = Rig(bus_pair, make_config(sim=NO_DIST))
    fb = rig.enable()
    fb = rig.step(5000, fb)
    assert fb.status == Status.ENABLED | Status.SATURATED
    assert rig.truth[-1].applied_current_A == 1433 * LSB  # the clamped current acted
    fb = rig.step(-1433, fb)
    assert fb.status == Status.ENABLED  # at the limit, not beyond it
    assert rig.truth[-1].applied_current_A == -1433 * LSB
    fb = rig.step(-1434, fb)
    assert fb.status == Status.ENABLED | Status.SATURATED
    assert rig.drive.stats.saturations == 2


def test_command_with_enable_clear_applies_zero_and_stays_enabled(
    bus_pair: tuple[can.BusABC, can.BusABC],
) -> None:
    rig = Rig(bus_pair, make_config(sim=NO_DIST))
    fb = rig.enable()
    fb = rig.step(1000, fb)
    fb = rig.step(1000, fb, enable=False)
    assert rig.truth[-1].applied_current_A == 0.0
    assert fb.status == Status.ENABLED and rig.drive.state is DriveState.ENABLED


def test_disable_zeroes_the_current_and_clear_fault_leads_to_disabled(
    bus_pair: tuple[can.BusABC, can.BusABC],
) -> None:
    rig = Rig(bus_pair, make_config(sim=NO_DIST))
    fb = rig.enable()
    fb = rig.step(1000, fb)
    rig.host.control(ControlRequest.DISABLE)
    rig.drive.service()
    assert rig.host.drain() == [HeartbeatFrame(DriveState.DISABLED)]
    fb = rig.step(1000, fb)  # time still advances on valid commands, but nothing is applied
    assert fb.status == Status(0)
    rig.step(1000, fb)
    assert rig.truth[-1].applied_current_A == 0.0 and rig.truth[-1].drive_state is DriveState.DISABLED
    # CLEAR_FAULT while not in FAULT changes nothing; the heartbeat says so
    rig.host.control(ControlRequest.CLEAR_FAULT)
    rig.drive.service()
    assert rig.host.drain() == [HeartbeatFrame(DriveState.DISABLED)]


def test_watchdog_trips_in_exactly_n_periods(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    n = 7
    rig = Rig(bus_pair, make_config(sim=NO_DIST, drive={"watchdog_periods": n}))
    fb = rig.enable()
    fb = rig.step(800, fb)
    for _ in range(n - 1):
        rig.drive.advance_period()
        frames = rig.host.drain()
        assert [type(f) for f in frames] == [FeedbackFrame]
        assert frames[0].status == Status.ENABLED  # type: ignore[union-attr]
        assert rig.truth[-1].applied_current_A == 800 * LSB  # the drive holds the last command
    rig.drive.advance_period()
    frames = rig.host.drain()
    assert frames[:2] == [FaultFrame(FaultCode.WATCHDOG, n), HeartbeatFrame(DriveState.FAULT)]
    assert feedbacks(frames)[0].status == Status.FAULT | Status.WATCHDOG
    assert rig.drive.state is DriveState.FAULT
    rig.drive.advance_period()
    assert rig.truth[-1].applied_current_A == 0.0  # zero from the trip on
    assert feedbacks(rig.host.drain())[0].status == Status.FAULT | Status.WATCHDOG
    # enable is refused in FAULT; clear fault, then enable again
    rig.host.control(ControlRequest.ENABLE)
    rig.drive.service()
    assert rig.host.drain() == [HeartbeatFrame(DriveState.FAULT)]
    rig.host.control(ControlRequest.CLEAR_FAULT)
    rig.drive.service()
    assert rig.host.drain() == [HeartbeatFrame(DriveState.DISABLED)]
    fb = rig.enable()
    assert fb.status == Status.ENABLED


def test_a_command_resets_the_watchdog(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    rig = Rig(bus_pair, make_config(sim=NO_DIST, drive={"watchdog_periods": 3}))
    fb = rig.enable()
    for _ in range(5):
        rig.drive.advance_period()
        rig.drive.advance_period()
        fb = feedbacks(rig.host.drain())[-1]
        fb = rig.step(0, fb)
    assert rig.drive.state is DriveState.ENABLED


def test_stale_and_duplicate_commands_are_ignored(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    rig = Rig(bus_pair, make_config(sim=NO_DIST))
    rig.host.command(100, 0)  # before any feedback
    assert rig.drive.service() == 1 and rig.host.drain() == []
    fb0 = rig.enable()
    fb1 = rig.step(100, fb0)
    rig.host.command(100, fb0.seq)  # answers an old sample
    rig.drive.service()
    assert rig.host.drain() == [] and rig.drive.period_index == 1
    assert rig.drive.stats.commands_stale == 2
    rig.step(100, fb1)
    assert rig.drive.period_index == 2


def test_command_sequence_wraps(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    rig = Rig(bus_pair, make_config(sim=NO_DIST))
    fb = rig.enable()
    seqs = []
    for _ in range(600):
        fb = rig.step(10, fb)
        seqs.append(fb.seq)
    assert seqs == [k % 256 for k in range(1, 601)]


def test_bad_frame_faults_the_drive(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    rig = Rig(bus_pair, make_config(sim=NO_DIST))
    rig.enable()
    rig.host.send_raw(FrameKind.COMMAND, b"\x01\x02")  # 2 bytes, not 3
    rig.drive.service()
    low_byte = (FrameKind.COMMAND + 1) & 0xFF  # 0xA1
    assert rig.host.drain() == [FaultFrame(FaultCode.BAD_FRAME, low_byte), HeartbeatFrame(DriveState.FAULT)]
    assert rig.drive.state is DriveState.FAULT
    rig.drive.advance_period()
    assert feedbacks(rig.host.drain())[0].status == Status.FAULT


def test_other_nodes_and_foreign_frames_are_ignored(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    rig = Rig(bus_pair, make_config(sim=NO_DIST, drive={"node_id": 5}))
    rig.host.send_raw(FrameKind.CONTROL, b"\x01", node_id=6)
    rig.host.bus.send(can.Message(arbitration_id=0x605, data=b"\x01", is_extended_id=True))
    rig.host.bus.send(can.Message(arbitration_id=0x123, data=b"", is_extended_id=False))
    assert rig.drive.service() == 3
    assert rig.drive.state is DriveState.DISABLED and rig.host.drain() == []
    fb = rig.enable()
    assert fb.seq == 0


def test_input_delay_applies_each_command_d_periods_later(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    no_design = {"estimator": {}, "feedback": {}, "dob": {}}  # the paper's gains have no delay state
    rig = Rig(bus_pair, make_config(sim=NO_DIST, plant={"input_delay_samples": 2}, design=no_design))
    fb = rig.enable()
    codes = [100, 200, 300, 400, 500, 600]
    for c in codes:
        fb = rig.step(c, fb)
    applied = [t.applied_current_A for t in rig.truth[1:]]  # current acting over period k
    assert applied == [0.0, 0.0] + [c * LSB for c in codes[:-2]]


def test_heartbeat_at_10_hz_of_simulated_time(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    rig = Rig(bus_pair, make_config(sim=NO_DIST))
    fb = rig.enable()
    heartbeats = []
    for k in range(1, 1001):  # 0.3 s
        rig.host.command(0, fb.seq)
        rig.drive.service()
        frames = rig.host.drain()
        fb = feedbacks(frames)[0]
        if any(isinstance(f, HeartbeatFrame) for f in frames):
            heartbeats.append(k)
    assert heartbeats == [334, 667, 1000]  # first period at or after 100, 200, 300 ms


def test_truth_carries_the_disturbance_at_the_sample_instant(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    rig = Rig(bus_pair, make_config())  # the paper's 0.2 sin(8 pi t)
    fb = rig.enable()
    for _ in range(50):
        fb = rig.step(0, fb)
    for t in rig.truth:
        assert t.disturbance_A == pytest.approx(0.2 * math.sin(8 * math.pi * t.time_ns * 1e-9), abs=1e-15)


def test_seeded_noise_and_loss_are_reproducible(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    sim = {"noise_counts_std": 2.0, "loss_probability": 0.1, "seed": 4}
    runs = []
    for _ in range(2):
        rig = Rig(bus_pair, make_config(sim=sim))
        fb = rig.enable()
        seen: list[tuple[int, int] | None] = []
        expected_seq = fb.seq
        for _ in range(300):
            rig.host.command(600, expected_seq)  # answer the sample the drive took, lost or not
            rig.drive.service()
            got = feedbacks(rig.host.drain())
            expected_seq = (expected_seq + 1) % 256
            seen.append((got[0].seq, got[0].counts) if got else None)
        runs.append(seen)
        assert rig.drive.stats.feedback_lost == seen.count(None) > 10
        assert len(rig.truth) == 301  # truth at every sample instant, lost or not
        noise = [
            got[1] - math.floor(t.state[0] * 10000 + 0.5)
            for got, t in zip(seen, rig.truth[1:], strict=True)
            if got is not None
        ]
        assert 1.5 < statistics.pstdev(noise) < 2.5
    assert runs[0] == runs[1]


def test_realtime_only_calls_are_refused_in_lockstep(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    drive = SimulatedDrive(bus_pair[1], make_config(), clock="realtime")
    with pytest.raises(RuntimeError, match="lockstep"):
        drive.service()
    with pytest.raises(RuntimeError, match="lockstep"):
        drive.advance_period()
    with pytest.raises(ValueError, match="clock"):
        SimulatedDrive(bus_pair[1], make_config(), clock="fast")  # type: ignore[arg-type]
