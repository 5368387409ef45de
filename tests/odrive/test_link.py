"""OdriveDriveLink: units, the current limit, malformed estimates, heartbeats, enable and stop."""

from __future__ import annotations

import math
import struct
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from dob_hil.config import Config
from dob_hil.errors import ConfigError, DriveFault
from dob_hil.link.base import LinkEventKind
from dob_hil.link.odrive import codec
from dob_hil.link.odrive.codec import AxisState, CmdId, Heartbeat, ODriveError
from dob_hil.link.odrive.link import TorqueQuantizer

from .odrive_support import NODE, Rig, make_rig, odrive_config

KT = 0.0827  # paper-step-odrive's torque constant


@pytest.fixture
def config(tmp_path: Path) -> Config:
    return odrive_config(tmp_path, cyclic=True)


@pytest.fixture
def rig(config: Config) -> Iterator[Rig]:
    r = make_rig(config)
    yield r
    r.close()


def kinds(rig: Rig) -> list[LinkEventKind]:
    return [e.kind for e in rig.events]


# --- the current limit and the torque command -----------------------------------------------------
@given(
    st.floats(0.01, 50.0),
    st.floats(1e-3, 10.0),
    st.floats(allow_nan=True, allow_infinity=True),
)
def test_applied_current_never_exceeds_the_limit(limit_A: float, kt: float, u: float) -> None:
    q = TorqueQuantizer(limit_A, kt)
    (code,), (applied,), saturated = q.quantize((u,))
    torque = codec.float32_from_bits(code)
    assert math.isfinite(torque)
    assert abs(torque) / kt <= limit_A and abs(applied) <= limit_A
    assert applied == torque / kt
    if math.isfinite(u) and abs(u) <= limit_A:
        assert abs(applied - u) <= 1e-6 * max(abs(u), 1e-30) + 1e-37 and not saturated
    if not math.isfinite(u):
        assert code == 0 and saturated


def test_command_is_float32_torque_through_the_torque_constant(rig: Rig) -> None:
    (code,), (applied,), saturated = rig.link.quantize((0.5,))
    assert codec.float32_from_bits(code) == pytest.approx(0.5 * KT, rel=1e-7) and not saturated
    rig.link.send_command((code,), 0)
    (sent,) = rig.sent()
    assert sent.arbitration_id == NODE << 5 | CmdId.SET_INPUT_TORQUE
    assert bytes(sent.data) == struct.pack("<f", codec.float32_from_bits(code)) + bytes(4)
    (code,), (applied,), saturated = rig.link.quantize((5.0,))
    assert saturated and applied == pytest.approx(0.7, rel=1e-6) and applied <= 0.7


def test_a_code_beyond_the_limit_is_clamped_on_the_wire(rig: Rig) -> None:
    rig.link.send_command((codec.float32_bits(100.0),), 0)
    rig.link.send_command((codec.float32_bits(math.nan),), 0)
    torques = [codec.decode_set_input_torque(m.data) for m in rig.sent()]
    assert torques[0] <= 0.7 * KT and torques[0] == pytest.approx(0.7 * KT) and torques[1] == 0.0
    assert rig.link.stats.clamped_commands == 2


def test_nonfinite_current_sends_zero_and_an_event(rig: Rig) -> None:
    (code,), (applied,), saturated = rig.link.quantize((math.nan,))
    assert (code, applied, saturated) == (0, 0.0, True)
    assert kinds(rig) == [LinkEventKind.INVALID_COMMAND]


@pytest.mark.parametrize("kt", [0.0, -1.0])
def test_torque_constant_must_be_positive(tmp_path: Path, kt: float) -> None:
    with pytest.raises(ConfigError, match=r"drive\.odrive\.torque_constant_Nm_per_A: must be > 0"):
        odrive_config(tmp_path, cyclic=True, odrive={"torque_constant_Nm_per_A": kt})


def test_torque_constant_must_be_finite(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="torque_constant_Nm_per_A: must be finite"):
        odrive_config(tmp_path, cyclic=True, odrive={"torque_constant_Nm_per_A": math.inf})


def test_encoder_rate_must_be_the_control_period(tmp_path: Path) -> None:
    from dob_hil.link.odrive.options import odrive_options

    with pytest.raises(
        ConfigError, match=r"encoder_msg_rate_ms: 2 ms must equal the control period \(1 ms\)"
    ):
        odrive_options(odrive_config(tmp_path, cyclic=True, odrive={"encoder_msg_rate_ms": 2}))


# --- receiving ------------------------------------------------------------------------------------
def estimates(pos: float, vel: float = 0.0) -> bytes:
    return struct.pack("<ff", pos, vel)


def test_estimates_are_quantized_to_the_encoder(rig: Rig) -> None:
    rig.inject(CmdId.GET_ENCODER_ESTIMATES, estimates(0.123456))
    fb = rig.link.receive_feedback(0)
    assert fb is not None
    assert fb.counts == (1235,) and fb.position == (0.1235,)  # 10000 counts per turn and per unit


@pytest.mark.parametrize(
    ("pos", "vel", "problem"),
    [
        (math.nan, 0.0, "non-finite"),
        (0.0, math.inf, "non-finite"),
        (-math.inf, 0.0, "non-finite"),
        (3.0e38, 0.0, "beyond the int32 count range"),
        (-1.0e6, 0.0, "beyond the int32 count range"),
    ],
)
def test_nan_inf_and_huge_estimates_are_malformed_never_fed(
    rig: Rig, pos: float, vel: float, problem: str
) -> None:
    rig.inject(CmdId.GET_ENCODER_ESTIMATES, estimates(pos, vel))
    assert rig.link.receive_feedback(0) is None
    assert kinds(rig) == [LinkEventKind.MALFORMED_FRAME] and problem in rig.events[0].message
    rig.inject(CmdId.GET_ENCODER_ESTIMATES, estimates(0.5))
    fb = rig.link.receive_feedback(0)
    assert fb is not None and fb.position == (0.5,)


def test_short_estimates_are_malformed(rig: Rig) -> None:
    rig.inject(CmdId.GET_ENCODER_ESTIMATES, bytes(6))
    assert rig.link.receive_feedback(0) is None
    assert "expected 8 bytes, got 6" in rig.events[0].message


def test_foreign_and_error_frames_are_events(rig: Rig) -> None:
    rig.drive_bus.send(
        can.Message(arbitration_id=(NODE + 1) << 5 | 9, data=estimates(9.0), is_extended_id=False)
    )
    rig.drive_bus.send(can.Message(arbitration_id=0x18FF50E5, data=bytes(8), is_extended_id=True))
    rig.drive_bus.send(can.Message(arbitration_id=NODE << 5 | 0x1F, data=bytes(8), is_extended_id=False))
    rig.drive_bus.send(can.Message(is_error_frame=True, arbitration_id=0x20000040, data=bytes(8)))
    rig.drive_bus.send(can.Message(arbitration_id=NODE << 5 | CmdId.SET_INPUT_TORQUE, data=bytes(8),
                                   is_extended_id=False))  # fmt: skip
    assert rig.link.receive_feedback(0) is None
    assert kinds(rig) == [LinkEventKind.FOREIGN_FRAME] * 3 + [LinkEventKind.ERROR_FRAME]
    assert rig.link.stats.own_echoes == 1


def test_sequence_numbers_come_from_arrival_times(rig: Rig) -> None:
    t0 = 1000.0
    for k in (0, 1, 2, 5, 6):  # 3 and 4 lost on the bus
        rig.drive_bus.send(can.Message(arbitration_id=NODE << 5 | 9, data=estimates(k / 10), timestamp=t0,
                                       is_extended_id=False))  # fmt: skip
    seqs = []
    for k in (0, 1, 2, 5, 6):
        msg = rig.host_bus.recv(1.0)
        assert msg is not None
        msg.timestamp = t0 + k * 1e-3 + (2e-4 if k == 2 else 0.0)  # stamped on arrival, with jitter
        rig.link._consume(msg)
        fb = rig.link._take()
        assert fb is not None
        seqs.append(fb.seq)
    assert seqs == [0, 1, 2, 5, 6] and rig.link.stats.missed_feedback == 2


def test_duplicates_and_reordered_estimates_are_stale(rig: Rig) -> None:
    msgs = [can.Message(arbitration_id=NODE << 5 | 9, data=estimates(k), timestamp=100.0 + k * 1e-3,
                        is_extended_id=False) for k in range(3)]  # fmt: skip
    for msg in (msgs[0], msgs[1], msgs[1], msgs[2], msgs[1]):
        rig.link._consume(msg)
    assert rig.link.stats.stale_feedback == 2 and rig.link.stats.feedback == 3
    assert kinds(rig) == [LinkEventKind.STALE_FEEDBACK] * 2


# --- enable, errors, stop -------------------------------------------------------------------------
def test_enable_sequence_and_safe_stop_frames(tmp_path: Path) -> None:
    rig = make_rig(odrive_config(tmp_path, cyclic=True, drive={"clear_fault": True}))
    try:
        rig.link.enable_lockstep(rig.drive.service)
        assert rig.drive.enabled
        rig.link.safe_stop()
        while rig.drive.service():
            pass
        sent = [(m.arbitration_id & 0x1F, bytes(m.data)) for m in rig.sent() if m.arbitration_id & 0x1F != 1]
        host = [s for s in sent if s[0] != CmdId.GET_ENCODER_ESTIMATES]
        assert host == [
            (CmdId.CLEAR_ERRORS, bytes(8)),
            (CmdId.SET_CONTROLLER_MODE, bytes.fromhex("0100000001000000")),
            (CmdId.SET_INPUT_TORQUE, bytes(8)),
            (CmdId.SET_AXIS_STATE, bytes.fromhex("0800000000000000")),
            (CmdId.SET_INPUT_TORQUE, bytes(8)),
            (CmdId.SET_AXIS_STATE, bytes.fromhex("0100000000000000")),
        ]
        assert not rig.drive.enabled
    finally:
        rig.close()


def test_enable_times_out_naming_the_axis_error_bits(rig: Rig) -> None:
    rig.drive._need_lockstep("test").core.set_error(ODriveError.DC_BUS_UNDER_VOLTAGE, 0)
    with pytest.raises(
        DriveFault,
        match=r"did not enter CLOSED_LOOP_CONTROL .*last heartbeat: IDLE, axis error 0x00000200 "
        r"\(DC_BUS_UNDER_VOLTAGE\)",
    ):
        rig.link.enable_lockstep(rig.drive.service)
    assert not rig.drive.enabled


def test_real_time_enable_times_out_naming_the_bits(rig: Rig) -> None:
    hb = codec.encode_heartbeat(
        Heartbeat(int(ODriveError.DRV_FAULT | ODriveError.MOTOR_OVER_TEMP), AxisState.IDLE)
    )
    rig.inject(CmdId.HEARTBEAT, hb)
    with pytest.raises(
        DriveFault, match=r"within 50 ms .*axis error 0x00002020 \(DRV_FAULT\|MOTOR_OVER_TEMP\)"
    ):
        rig.link.enable(50_000_000)


def test_axis_error_in_a_heartbeat_ends_the_run_with_its_name(rig: Rig) -> None:
    rig.link.enable_lockstep(rig.drive.service)
    assert rig.link.receive_feedback(0) is not None
    rig.inject(CmdId.HEARTBEAT, codec.encode_heartbeat(Heartbeat(0x4000000, AxisState.IDLE)))
    with pytest.raises(
        DriveFault, match=r"left closed loop: IDLE, axis error 0x04000000 \(SPINOUT_DETECTED\)"
    ):
        rig.link.receive_feedback(0)
    assert LinkEventKind.DRIVE_FAULT in kinds(rig)


def test_node_id_beyond_63_is_refused(tmp_path: Path) -> None:
    config = odrive_config(tmp_path, cyclic=True, drive={"node_id": 64})
    with pytest.raises(ConfigError, match=r"drive\.node_id: ODrive node id must be 0\.\.63"):
        make_rig(config)
