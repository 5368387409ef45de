"""The multi-axis native link: routing by node, one feedback per period, per-axis commands, all-or-nothing
stop (dob_hil.link.native_axes), checked frame by frame against a hand-driven bus end."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

import can
import pytest
from mimo_support import mimo_config

from dob_hil.config import Config, DriveConfig
from dob_hil.errors import ConfigError, DriveFault, ProtocolError
from dob_hil.link import protocol
from dob_hil.link.axes import axis_node_ids
from dob_hil.link.base import LinkEvent, LinkEventKind
from dob_hil.link.busload import worst_case_bus_load
from dob_hil.link.native_axes import MultiAxisNativeLink
from dob_hil.link.protocol import ControlRequest, DriveState, FaultCode, FrameKind, Status
from dob_hil.loop.inproc_bus import bus_pair
from dob_hil.profiles import get_profile
from firmware_sim.axes import MultiAxisDrive

PERIOD_NS = 500_000
ENABLED = Status.ENABLED


class FakeDrives:
    """The drive end of an in-process bus, sending frames by hand."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus

    def feedback(self, node: int, seq: int, counts: int, status: Status = ENABLED) -> None:
        payload = protocol.encode_feedback(protocol.FeedbackFrame(counts, seq, status))
        self.send(FrameKind.FEEDBACK + node, payload)

    def heartbeat(self, node: int, state: DriveState) -> None:
        self.send(FrameKind.HEARTBEAT + node, protocol.encode_heartbeat(protocol.HeartbeatFrame(state)))

    def fault(self, node: int, code: FaultCode) -> None:
        self.send(FrameKind.FAULT + node, protocol.encode_fault(protocol.FaultFrame(code, 0)))

    def send(self, arbitration_id: int, data: bytes, **kw: bool) -> None:
        self.bus.send(can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False, **kw))

    def received(self) -> list[can.Message]:
        out = []
        while (msg := self.bus.recv(0.0)) is not None:
            out.append(msg)
        return out


@pytest.fixture
def drive_cfg(mimo: Config) -> DriveConfig:
    return dataclasses.replace(mimo.drive, node_ids=(3, 5), feedback_timeout_periods=10)


class Clock:
    def __init__(self) -> None:
        self.now_ns = 1_000_000_000

    def __call__(self) -> int:
        return self.now_ns


@pytest.fixture
def pair(drive_cfg: DriveConfig) -> Iterator[tuple[MultiAxisNativeLink, FakeDrives, list[LinkEvent], Clock]]:
    host, drive_end = bus_pair("mimo-link")
    events: list[LinkEvent] = []
    clock = Clock()
    link = MultiAxisNativeLink(host, drive_cfg, 2, event_hook=events.append, clock_ns=clock, owns_bus=True,
                               period_ns=PERIOD_NS)  # fmt: skip
    yield link, FakeDrives(drive_end), events, clock
    link.close()
    drive_end.shutdown()


def test_frames_of_two_nodes_interleaved_give_one_feedback_per_period_in_axis_order(pair) -> None:  # type: ignore[no-untyped-def]
    link, drives, _, _ = pair
    drives.feedback(5, 0, 200)  # node 5 first: axis 1
    drives.feedback(3, 0, 100)
    drives.feedback(3, 1, 101)
    drives.feedback(5, 1, 201)
    fb0 = link.receive_feedback(0)
    fb1 = link.receive_feedback(0)
    assert fb0 is not None and fb1 is not None
    assert (fb0.seq, fb0.counts, fb0.raw_counts) == (0, (100, 200), (100, 200))
    assert (fb1.seq, fb1.counts) == (1, (101, 201))
    assert fb1.position == pytest.approx((101 / 10000.0, 201 / 10000.0))
    assert fb1.enabled and not fb1.fault and not fb1.saturated
    assert link.receive_feedback(0) is None
    assert link.stats.periods == 2 and link.stats.incomplete_periods == 0


def test_a_period_waits_for_its_late_axis_and_is_delivered_whole(pair) -> None:  # type: ignore[no-untyped-def]
    link, drives, _, _ = pair
    drives.feedback(3, 7, 100)
    assert link.receive_feedback(0) is None  # node 5's frame of period 7 is not in yet
    drives.feedback(5, 7, 200)
    fb = link.receive_feedback(0)
    assert fb is not None and (fb.seq, fb.counts) == (7, (100, 200))


def test_a_period_missing_an_axis_is_given_up_when_a_newer_one_completes_never_mixed(pair) -> None:  # type: ignore[no-untyped-def]
    link, drives, events, _ = pair
    drives.feedback(3, 7, 100)
    drives.feedback(3, 8, 110)  # node 5's FEEDBACK of period 7 is lost
    drives.feedback(5, 8, 210)
    fb = link.receive_feedback(0)
    assert fb is not None and (fb.seq, fb.counts) == (8, (110, 210))
    assert link.stats.incomplete_periods == 1
    assert any("seq 7 incomplete" in e.message and "[5]" in e.message for e in events)
    drives.feedback(5, 7, 200)  # the lost one turns up after all: stale, never delivered
    assert link.receive_feedback(0) is None
    assert link.stats.axes[1].stale_feedback == 1  # node 5's own link: older than its seq 8


def test_a_partial_period_past_the_host_timeout_counts_as_missing(pair) -> None:  # type: ignore[no-untyped-def]
    link, drives, events, clock = pair
    drives.feedback(3, 4, 100)
    assert link.receive_feedback(0) is None
    clock.now_ns += 11 * PERIOD_NS  # beyond feedback_timeout_periods = 10
    assert link.receive_feedback(0) is None
    assert link.stats.incomplete_periods == 1
    assert any("past the host timeout" in e.message for e in events)
    drives.feedback(5, 4, 200)
    assert link.receive_feedback(0) is None  # too late: stale
    drives.feedback(3, 5, 101)
    drives.feedback(5, 5, 201)
    fb = link.receive_feedback(0)
    assert fb is not None and fb.seq == 5


def test_stale_and_duplicate_feedback_of_one_axis_is_discarded(pair) -> None:  # type: ignore[no-untyped-def]
    link, drives, events, _ = pair
    for seq in (10, 11):
        drives.feedback(3, seq, seq)
        drives.feedback(5, seq, -seq)
    assert [fb.seq for fb in iter(lambda: link.receive_feedback(0), None)] == [10, 11]
    drives.feedback(3, 10, 10)  # node 3 repeats an old period
    drives.feedback(3, 12, 12)
    drives.feedback(5, 12, -12)
    fb = link.receive_feedback(0)
    assert fb is not None and fb.seq == 12 and fb.counts == (12, -12)
    assert link.stats.axes[0].stale_feedback == 1  # the axis's own link caught it
    assert any(e.kind is LinkEventKind.STALE_FEEDBACK for e in events)


def test_frames_of_a_foreign_node_and_other_ids_are_reported_and_skipped(pair) -> None:  # type: ignore[no-untyped-def]
    link, drives, events, _ = pair
    drives.feedback(4, 0, 999)  # node 4 is no axis of ours
    drives.send(0x123, b"\x01")
    drives.send(0x6B3, b"\x00" * 6, is_remote_frame=True)
    drives.bus.send(can.Message(arbitration_id=0x6B3, data=b"\x00" * 6, is_extended_id=True))
    drives.bus.send(can.Message(arbitration_id=0x4, is_error_frame=True))
    drives.feedback(3, 0, 100)
    drives.feedback(5, 0, 200)
    fb = link.receive_feedback(0)
    assert fb is not None and fb.counts == (100, 200)
    kinds = [e.kind for e in events]
    assert kinds.count(LinkEventKind.FOREIGN_FRAME) == 4 and kinds.count(LinkEventKind.ERROR_FRAME) == 1
    assert link.stats.foreign_frames == 4 and link.stats.error_frames == 1
    assert any("0x6B4" in e.message and "[3, 5]" in e.message for e in events)


def test_waiting_blocks_until_the_period_completes_on_a_threaded_bus(drive_cfg: DriveConfig) -> None:
    host, drive_end = bus_pair("mimo-wait", "virtual")
    try:
        link = MultiAxisNativeLink(host, drive_cfg, 2)
        drives = FakeDrives(drive_end)
        drives.feedback(3, 0, 1)
        drives.feedback(5, 0, 2)
        fb = link.receive_feedback(5_000_000_000)  # patient: the frames are there at once
        assert fb is not None and fb.counts == (1, 2)
        assert link.receive_feedback(1_000_000) is None  # nothing more: the wait ends
        link.close()
    finally:
        host.shutdown()
        drive_end.shutdown()


def test_quantize_limits_each_axis_with_its_dac_and_send_command_sends_one_command_per_node(pair) -> None:  # type: ignore[no-untyped-def]
    link, drives, events, _ = pair
    codes, applied, saturated = link.quantize((5.0, -0.1))
    assert codes == (1433, -205) and saturated
    assert applied == (1433 / 2048, -205 / 2048)
    codes, applied, saturated = link.quantize((0.01, float("nan")))
    assert codes == (20, 0) and applied[1] == 0.0 and saturated
    assert any(e.kind is LinkEventKind.INVALID_COMMAND and "node 5" in e.message for e in events)
    with pytest.raises(ProtocolError, match="2 axes, got 1"):
        link.quantize((0.1,))
    link.send_command((100, -200), 300)
    sent = drives.received()
    assert [(m.arbitration_id, protocol.decode_command(m.data)) for m in sent] == [
        (FrameKind.COMMAND + 3, protocol.CommandFrame(100, 300 % 128, False)),
        (FrameKind.COMMAND + 5, protocol.CommandFrame(-200, 300 % 128, False)),
    ]
    with pytest.raises(ProtocolError):
        link.send_command((1,), 0)


def test_an_axis_fault_stops_every_axis_at_zero_current(pair) -> None:  # type: ignore[no-untyped-def]
    link, drives, _, _ = pair
    for node in (3, 5):
        drives.feedback(node, 0, 0)
        drives.heartbeat(node, DriveState.ENABLED)
    for axis in link.axes:
        axis.request_enable()
    assert all(axis.poll_enabled() for axis in link.axes)
    drives.received()
    assert link.receive_feedback(0) is not None
    drives.fault(5, FaultCode.OVERCURRENT)
    drives.feedback(3, 1, 0)
    drives.feedback(5, 1, 0, Status.FAULT)
    with pytest.raises(DriveFault, match="node 5 reports a fault: OVERCURRENT"):
        link.receive_feedback(0)
    link.safe_stop()
    sent = drives.received()
    commands = [(m.arbitration_id, protocol.decode_command(m.data)) for m in sent if m.dlc == 3]
    controls = [(m.arbitration_id, protocol.decode_control(m.data).request) for m in sent if m.dlc == 2]
    assert {aid for aid, _ in commands} == {FrameKind.COMMAND + 3, FrameKind.COMMAND + 5}
    assert all(c.current_counts == 0 and not c.enable for _, c in commands)
    assert sorted(controls) == [(FrameKind.CONTROL + 3, ControlRequest.DISABLE),
                                (FrameKind.CONTROL + 5, ControlRequest.DISABLE)]  # fmt: skip
    assert link.fault_description is not None and "node 5" in link.fault_description


def test_against_the_simulated_drive_an_injected_axis_fault_leaves_both_axes_off(mimo: Config) -> None:
    host, drive_end = bus_pair("mimo-fault")
    drive = MultiAxisDrive(drive_end, mimo)
    link = MultiAxisNativeLink(host, mimo.drive, 2)
    link.enable_lockstep(drive.service)
    assert drive.axis_states == (DriveState.ENABLED, DriveState.ENABLED)
    for _ in range(20):
        fb = link.receive_feedback(0)
        assert fb is not None and fb.enabled
        codes, _, _ = link.quantize((0.3, -0.3))
        link.send_command(codes, fb.seq)
        drive.service()
    assert drive.applied_currents_A == (614 / 2048, -614 / 2048)
    core = drive._lockstep.core  # type: ignore[union-attr]
    core.axes[1].fault(FaultCode.OVERCURRENT, 0, core.time_ns)  # node 2's power stage trips
    fb = link.receive_feedback(0)
    assert fb is not None  # the period already sampled before the fault
    link.send_command(link.quantize((0.3, -0.3))[0], fb.seq)
    drive.service()
    with pytest.raises(DriveFault, match="node 2 reports a fault"):
        link.receive_feedback(0)
    link.safe_stop()
    while drive.service():
        pass
    assert drive.axis_states == (DriveState.DISABLED, DriveState.FAULT)
    assert drive.applied_currents_A == (0.0, 0.0)
    link.close()


def test_enable_lockstep_enables_every_node_and_the_first_period_has_both_enabled(mimo: Config) -> None:
    host, drive_end = bus_pair("mimo-enable")
    drive = MultiAxisDrive(drive_end, mimo)
    link = MultiAxisNativeLink(host, mimo.drive, 2)
    link.enable_lockstep(drive.service)
    fb = link.receive_feedback(0)
    assert fb is not None and fb.seq == 0 and fb.enabled
    link.close()
    while drive.service():
        pass
    assert drive.axis_states == (DriveState.DISABLED, DriveState.DISABLED)


# ---- configuration ------------------------------------------------------------------------------


def test_node_ids_default_to_consecutive_nodes_and_are_checked(mimo: Config) -> None:
    drive = dataclasses.replace(mimo.drive, node_id=4, node_ids=None)
    assert axis_node_ids(drive, 3) == (4, 5, 6)
    with pytest.raises(ConfigError, match=r"drive\.node_id: 3 axes from node 14"):
        axis_node_ids(dataclasses.replace(drive, node_id=14), 3)
    with pytest.raises(ConfigError, match=r"drive.node_ids: expected 2 node ids .*got 3"):
        axis_node_ids(dataclasses.replace(drive, node_ids=(1, 2, 3)), 2)
    with pytest.raises(ConfigError, match=r"drive.node_ids: entry \[1\] must be in 0..15, got 16"):
        axis_node_ids(dataclasses.replace(drive, node_ids=(1, 16)), 2)


def test_config_refuses_repeated_node_ids_in_one_line() -> None:
    with pytest.raises(ConfigError, match=r"drive.node_ids: must be distinct, got \[2, 2\]"):
        mimo_config({"node_ids = [1, 2]": "node_ids = [2, 2]"})


def test_a_non_square_plant_is_refused_on_a_drive(mimo: Config) -> None:
    plant = dataclasses.replace(mimo.plant, C=mimo.plant.C[:1, :])
    config = dataclasses.replace(mimo, plant=plant)
    profile = get_profile("native")
    host, drive_end = bus_pair("mimo-square")
    for build in (lambda: profile.make_link(host, config, lambda m, r: None, lambda e: None),
                  lambda: profile.make_sim(drive_end, config, "lockstep", None)):  # fmt: skip
        with pytest.raises(ConfigError, match=r"plant\.C: a drive runs one axis per input and output"):
            build()


def test_the_bus_load_counts_every_axis(mimo: Config) -> None:
    one = worst_case_bus_load(mimo.drive, mimo.plant.period_ns)
    two = get_profile("native").bus_load(mimo)
    assert two.frames_per_period["FEEDBACK"] == 2 and two.frames_per_period["COMMAND"] == 2
    assert two.bits_per_period == pytest.approx(2 * one.bits_per_period)
    assert 0.39 < two.fraction < 0.41  # 40 % at 1 ms (the scenario's comment)


def test_the_profile_picks_the_multi_axis_link_and_drive(mimo: Config) -> None:
    profile = get_profile("native")
    host, drive_end = bus_pair("mimo-profile")
    link = profile.make_link(host, mimo, lambda m, r: None, lambda e: None)
    sim = profile.make_sim(drive_end, mimo, "lockstep", None)
    assert isinstance(link, MultiAxisNativeLink) and link.node_ids == (1, 2)
    assert isinstance(sim, MultiAxisDrive) and sim.node_ids == (1, 2)
    link.close()


def test_the_replay_quantizer_is_the_links_per_axis_and_dacquantizer_for_one_axis(pair, drive_cfg) -> None:  # type: ignore[no-untyped-def]
    import random

    from dob_hil.link.native import DacQuantizer
    from dob_hil.link.native_axes import axes_quantizer

    link = pair[0]
    quantize = axes_quantizer(drive_cfg)
    one = DacQuantizer(drive_cfg).quantize
    rng = random.Random(3)
    for _ in range(2000):
        u = (rng.uniform(-1.0, 1.0), rng.choice([rng.uniform(-1.0, 1.0), 0.5 / 2048, -1.5 / 2048, 9.0]))
        assert quantize(u) == link.quantize(u)
        assert quantize(u[:1]) == one(u[:1])


@pytest.mark.parametrize("clear_fault", [False, True])
def test_a_node_left_in_fault_refuses_the_enable_of_all_unless_cleared(
    mimo: Config, clear_fault: bool
) -> None:
    config = dataclasses.replace(mimo, drive=dataclasses.replace(mimo.drive, clear_fault=clear_fault))
    host, drive_end = bus_pair("mimo-refuse")
    drive = MultiAxisDrive(drive_end, config)
    core = drive._lockstep.core  # type: ignore[union-attr]
    core.axes[1].fault(FaultCode.OVERCURRENT, 0, 0)  # node 2 left in FAULT (a killed run, say)
    link = MultiAxisNativeLink(host, config.drive, 2)
    if clear_fault:
        link.enable_lockstep(drive.service)
        assert drive.axis_states == (DriveState.ENABLED, DriveState.ENABLED)
    else:
        with pytest.raises(DriveFault, match=r"node 2: the drive (refuses to enable|faulted).*--clear-fault"):
            link.enable_lockstep(drive.service)
        while drive.service():
            pass
        assert drive.axis_states == (DriveState.DISABLED, DriveState.FAULT)  # node 1 stopped again
    link.close()
