"""The simulated ODrive as a CANSimple user sees it: state machine, controller mode, torque input,
watchdog, Clear_Errors, heartbeats, estimates on the period and on RTR, injected faults."""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from dob_hil.errors import DriveFault
from dob_hil.link.odrive import codec
from dob_hil.link.odrive.codec import AxisState, CmdId, ControlMode, InputMode, ODriveError
from firmware_sim.odrive import SimulatedOdrive

from .odrive_support import NODE, Rig, make_rig, odrive_config

WATCHDOG = 10  # paper-step-odrive's watchdog_periods


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    r = make_rig(odrive_config(tmp_path, cyclic=True))
    yield r
    r.close()


def host_send(rig: Rig, cmd: CmdId, data: bytes = b"", *, remote: bool = False) -> None:
    rig.host_bus.send(can.Message(arbitration_id=NODE << 5 | cmd, data=None if remote else data, dlc=8,
                                  is_remote_frame=remote, is_extended_id=False))  # fmt: skip


def drive_frames(rig: Rig) -> list[tuple[int, bytes]]:
    out = []
    while (msg := rig.host_bus.recv(0.0)) is not None:
        out.append((msg.arbitration_id & 0x1F, bytes(msg.data)))
    return out


def heartbeats(frames: list[tuple[int, bytes]]) -> list[codec.Heartbeat]:
    return [codec.decode_heartbeat(d) for c, d in frames if c == CmdId.HEARTBEAT]


def core(rig: Rig):  # type: ignore[no-untyped-def]
    return rig.drive._need_lockstep("test").core


def enable(rig: Rig) -> None:
    mode = codec.encode_set_controller_mode(ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH)
    host_send(rig, CmdId.SET_CONTROLLER_MODE, mode)
    host_send(rig, CmdId.SET_AXIS_STATE, codec.encode_set_axis_state(AxisState.CLOSED_LOOP_CONTROL))
    rig.drive.service()


def test_closed_loop_is_announced_and_sampled(rig: Rig) -> None:
    enable(rig)
    frames = drive_frames(rig)
    assert heartbeats(frames)[-1] == codec.Heartbeat(0, AxisState.CLOSED_LOOP_CONTROL)
    assert frames[-1] == (CmdId.GET_ENCODER_ESTIMATES, struct.pack("<ff", 0.0, 0.0))
    assert rig.drive.enabled


def test_torque_acts_through_the_torque_constant_and_is_clamped(rig: Rig) -> None:
    enable(rig)
    host_send(rig, CmdId.SET_INPUT_TORQUE, codec.encode_set_input_torque(0.5 * 0.0827))
    rig.drive.service()
    assert core(rig).path.held_A == pytest.approx(0.5)
    host_send(rig, CmdId.SET_INPUT_TORQUE, codec.encode_set_input_torque(10.0))
    rig.drive.service()
    rig.drive.advance_period()
    assert core(rig).path.held_A == 0.7 and core(rig).stats.saturations == 1
    pos, vel = struct.unpack("<ff", drive_frames(rig)[-1][1])
    assert pos > 0 and vel > 0  # the plant moved forward


def test_no_current_outside_torque_passthrough(rig: Rig) -> None:
    mode = codec.encode_set_controller_mode(ControlMode.VELOCITY_CONTROL, InputMode.PASSTHROUGH)
    host_send(rig, CmdId.SET_CONTROLLER_MODE, mode)
    host_send(rig, CmdId.SET_AXIS_STATE, codec.encode_set_axis_state(AxisState.CLOSED_LOOP_CONTROL))
    rig.drive.service()
    host_send(rig, CmdId.SET_INPUT_TORQUE, codec.encode_set_input_torque(0.05))
    rig.drive.service()
    rig.drive.advance_period()
    assert core(rig).path.held_A == 0.0


def test_watchdog_expires_after_the_configured_periods_and_idles(rig: Rig) -> None:
    enable(rig)
    host_send(rig, CmdId.SET_INPUT_TORQUE, codec.encode_set_input_torque(0.05))
    rig.drive.service()
    for _ in range(WATCHDOG - 1):
        rig.drive.advance_period()
    assert rig.drive.enabled and core(rig).axis_error == 0
    rig.drive.advance_period()  # the 10th period in a row without a torque input
    assert not rig.drive.enabled
    assert core(rig).axis_error == ODriveError.WATCHDOG_TIMER_EXPIRED
    for _ in range(10):  # the next heartbeat (every 10 ms) reports it
        rig.drive.advance_period()
    assert core(rig).path.held_A == 0.0  # from the trip on
    assert any(hb.axis_error == ODriveError.WATCHDOG_TIMER_EXPIRED for hb in heartbeats(drive_frames(rig)))


def test_torque_inputs_feed_the_watchdog(rig: Rig) -> None:
    enable(rig)
    for _ in range(5 * WATCHDOG):
        host_send(rig, CmdId.SET_INPUT_TORQUE, codec.encode_set_input_torque(0.0))
        rig.drive.service()
    assert rig.drive.enabled and core(rig).axis_error == 0


def test_closed_loop_refused_with_an_active_error_until_clear_errors(rig: Rig) -> None:
    core(rig).set_error(ODriveError.DRV_FAULT, 0)
    enable(rig)
    assert not rig.drive.enabled
    assert heartbeats(drive_frames(rig))[-1] == codec.Heartbeat(int(ODriveError.DRV_FAULT), AxisState.IDLE)
    host_send(rig, CmdId.CLEAR_ERRORS, codec.encode_clear_errors())
    enable(rig)
    assert rig.drive.enabled
    assert heartbeats(drive_frames(rig))[-1] == codec.Heartbeat(0, AxisState.CLOSED_LOOP_CONTROL)


def test_link_clear_fault_recovers_a_drive_with_errors(tmp_path: Path) -> None:
    rig = make_rig(odrive_config(tmp_path, cyclic=True, drive={"clear_fault": True}))
    try:
        core(rig).set_error(ODriveError.WATCHDOG_TIMER_EXPIRED, 0)
        rig.link.enable_lockstep(rig.drive.service)
        assert rig.drive.enabled
    finally:
        rig.close()
    rig = make_rig(odrive_config(tmp_path, cyclic=True, drive={"clear_fault": False}))
    try:
        core(rig).set_error(ODriveError.WATCHDOG_TIMER_EXPIRED, 0)
        with pytest.raises(DriveFault, match="WATCHDOG_TIMER_EXPIRED"):
            rig.link.enable_lockstep(rig.drive.service)
    finally:
        rig.close()


def test_rtr_is_answered_with_the_estimates_of_the_instant(rig: Rig) -> None:
    enable(rig)
    drive_frames(rig)
    rig.link.send_sync()
    rig.drive.service()
    assert drive_frames(rig) == [(CmdId.GET_ENCODER_ESTIMATES, struct.pack("<ff", 0.0, 0.0))]
    assert rig.drive.stats.rtr_answered == 1
    request, answer = rig.sent()[-2:]
    assert request.is_remote_frame and request.arbitration_id == NODE << 5 | 0x09 and request.dlc == 8
    assert answer.arbitration_id == request.arbitration_id and not answer.is_remote_frame


def test_heartbeat_at_its_rate(rig: Rig) -> None:
    enable(rig)
    drive_frames(rig)
    for _ in range(100):
        host_send(rig, CmdId.SET_INPUT_TORQUE, codec.encode_set_input_torque(0.0))
        rig.drive.service()
    frames = drive_frames(rig)
    assert len(heartbeats(frames)) == 10  # 10 ms in 100 ms
    assert sum(c == CmdId.GET_ENCODER_ESTIMATES for c, _ in frames) == 100


def test_undecodable_frames_are_ignored(rig: Rig) -> None:
    host_send(rig, CmdId.SET_AXIS_STATE, struct.pack("<I4x", 99))
    rig.host_bus.send(can.Message(arbitration_id=NODE << 5 | CmdId.SET_INPUT_TORQUE, data=b"\x00",
                                  is_extended_id=False))  # fmt: skip
    host_send(rig, CmdId.SET_INPUT_TORQUE, struct.pack("<f4x", float("nan")))
    rig.drive.service()
    assert core(rig).stats.bad_frames == 3 and not rig.drive.enabled


def test_injected_drive_fault_sets_drv_fault(tmp_path: Path) -> None:
    config = odrive_config(tmp_path, cyclic=True, extra="\n[sim.faults]\nfault_at_s = 0.005\n")
    bus = can.Bus(interface="virtual", channel="he-odrive-fault", receive_own_messages=False)
    host = can.Bus(interface="virtual", channel="he-odrive-fault", receive_own_messages=False)
    try:
        drive = SimulatedOdrive(bus, config)
        host.send(can.Message(arbitration_id=NODE << 5 | 0x0B, data=bytes.fromhex("0100000001000000"),
                              is_extended_id=False))  # fmt: skip
        host.send(can.Message(arbitration_id=NODE << 5 | 0x07, data=bytes.fromhex("0800000000000000"),
                              is_extended_id=False))  # fmt: skip
        drive.service()
        for _ in range(5):
            assert drive.enabled
            drive.advance_period()
        assert not drive.enabled and drive.axis_error == ODriveError.DRV_FAULT
    finally:
        bus.shutdown()
        host.shutdown()
