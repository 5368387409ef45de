"""The ODrive CANSimple codec: byte-exact frames, round trips, and the shipped DBC read by cantools
as an independent decoder/encoder of every frame, both ways."""

from __future__ import annotations

import math
import struct
from importlib import resources
from typing import Any

import cantools
import pytest
from hypothesis import given
from hypothesis import strategies as st

from dob_hil.errors import ProtocolError
from dob_hil.link.odrive import codec
from dob_hil.link.odrive.codec import AxisState, CmdId, ControlMode, Heartbeat, InputMode, ODriveError

finite_f32 = st.floats(width=32, allow_nan=False, allow_infinity=False)


@pytest.fixture(scope="module")
def db() -> Any:
    with resources.as_file(resources.files("dob_hil.link.odrive") / "odrive_cansimple.dbc") as path:
        return cantools.database.load_file(str(path))


# --- byte-exact ----------------------------------------------------------------------------------
def test_arbitration_ids_are_node_shifted_by_five() -> None:
    assert codec.arbitration_id(0, CmdId.HEARTBEAT) == 0x001
    assert codec.arbitration_id(1, CmdId.SET_INPUT_TORQUE) == 0x02E
    assert codec.arbitration_id(3, CmdId.GET_ENCODER_ESTIMATES) == 0x069
    assert codec.arbitration_id(63, CmdId.CLEAR_ERRORS) == 0x7F8
    assert codec.split_id(0x7F8) == (63, 0x18)
    for bad in (-1, 64, True):
        with pytest.raises(ProtocolError, match=r"node id must be 0\.\.63"):
            codec.arbitration_id(bad, CmdId.HEARTBEAT)


def test_command_ids_are_odrives() -> None:
    assert {c.name: int(c) for c in CmdId} == {
        "HEARTBEAT": 0x01,
        "SET_AXIS_STATE": 0x07,
        "GET_ENCODER_ESTIMATES": 0x09,
        "SET_CONTROLLER_MODE": 0x0B,
        "SET_INPUT_TORQUE": 0x0E,
        "CLEAR_ERRORS": 0x18,
    }


def test_heartbeat_bytes() -> None:
    hb = Heartbeat(int(ODriveError.WATCHDOG_TIMER_EXPIRED), AxisState.IDLE, 0, False)
    assert codec.encode_heartbeat(hb) == bytes.fromhex("00 00 00 01 01 00 00 00")
    closed = Heartbeat(0, AxisState.CLOSED_LOOP_CONTROL, 0, True)
    assert codec.encode_heartbeat(closed) == bytes.fromhex("00 00 00 00 08 00 01 00")
    assert codec.decode_heartbeat(bytes.fromhex("20 00 00 00 08 02 01 00")) == Heartbeat(
        0x20, AxisState.CLOSED_LOOP_CONTROL, 2, True
    )


def test_command_frame_bytes() -> None:
    assert codec.encode_set_axis_state(AxisState.CLOSED_LOOP_CONTROL) == bytes.fromhex(
        "08 00 00 00 00 00 00 00"
    )
    assert codec.encode_set_axis_state(AxisState.IDLE) == bytes.fromhex("01 00 00 00 00 00 00 00")
    assert codec.encode_set_controller_mode(
        ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH
    ) == bytes.fromhex("01 00 00 00 01 00 00 00")
    assert codec.encode_set_input_torque(1.0) == bytes.fromhex("00 00 80 3f 00 00 00 00")
    assert codec.encode_set_input_torque(-0.5) == bytes.fromhex("00 00 00 bf 00 00 00 00")
    assert codec.encode_clear_errors() == bytes(8)
    assert codec.encode_encoder_estimates(codec.EncoderEstimates(1.5, -2.0)) == bytes.fromhex(
        "00 00 c0 3f 00 00 00 c0"
    )


def test_error_names() -> None:
    assert codec.error_names(0) == "none"
    assert codec.error_names(0x1000020) == "DRV_FAULT|WATCHDOG_TIMER_EXPIRED"
    assert codec.error_names(0x80) == "bit 0x80"


# --- bad input ------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("decode", "data", "problem"),
    [
        (codec.decode_heartbeat, bytes(7), "Heartbeat: expected 8 bytes, got 7"),
        (codec.decode_heartbeat, bytes.fromhex("00000000 05 000000"), "unknown Axis_State 5"),
        (codec.decode_set_axis_state, bytes.fromhex("63000000 00000000"), "unknown Axis_Requested_State 99"),
        (codec.decode_encoder_estimates, bytes(4), "Get_Encoder_Estimates: expected 8 bytes"),
        (codec.decode_set_controller_mode, bytes.fromhex("09000000 01000000"), "unknown Control_Mode 9"),
        (codec.decode_set_input_torque, bytes(9), "expected 8 bytes, got 9"),
        (codec.decode_clear_errors, b"", "expected 8 bytes, got 0"),
    ],
)
def test_decoders_name_what_is_wrong(decode: Any, data: bytes, problem: str) -> None:
    with pytest.raises(ProtocolError, match=problem):
        decode(data)


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, 1e39, -3.5e38])
def test_torque_that_is_not_a_finite_float32_is_never_encoded(value: float) -> None:
    with pytest.raises(ProtocolError, match="not a finite float32"):
        codec.encode_set_input_torque(value)


def test_estimates_carry_nan_and_inf_as_sent() -> None:
    est = codec.decode_encoder_estimates(struct.pack("<ff", math.nan, -math.inf))
    assert math.isnan(est.pos_turns) and est.vel_turns_s == -math.inf


# --- round trips ----------------------------------------------------------------------------------
@given(finite_f32, finite_f32)
def test_estimates_round_trip(pos: float, vel: float) -> None:
    est = codec.EncoderEstimates(pos, vel)
    assert codec.decode_encoder_estimates(codec.encode_encoder_estimates(est)) == est


@given(finite_f32)
def test_torque_round_trip_and_code_bits(torque: float) -> None:
    assert codec.decode_set_input_torque(codec.encode_set_input_torque(torque)) == torque
    assert codec.float32_from_bits(codec.float32_bits(torque)) == torque


@given(st.integers(0, 2**32 - 1), st.sampled_from(AxisState), st.integers(0, 255), st.booleans())
def test_heartbeat_round_trip(error: int, state: AxisState, result: int, done: bool) -> None:
    hb = Heartbeat(error, state, result, done)
    assert codec.decode_heartbeat(codec.encode_heartbeat(hb)) == hb


# --- cantools against the DBC, both ways ----------------------------------------------------------
def test_dbc_names_the_codecs_frames(db: Any) -> None:
    assert {m.frame_id: m.name for m in db.messages} == {
        1: "Heartbeat",
        7: "Set_Axis_State",
        9: "Get_Encoder_Estimates",
        11: "Set_Controller_Mode",
        14: "Set_Input_Torque",
        24: "Clear_Errors",
    }
    assert all(m.length == codec.DLC for m in db.messages)


@given(st.integers(0, 2**32 - 1), st.sampled_from(AxisState), st.integers(0, 255), st.booleans())
def test_dbc_heartbeat_both_ways(db: Any, error: int, state: AxisState, result: int, done: bool) -> None:
    hb = Heartbeat(error, state, result, done)
    signals = {
        "Axis_Error": error,
        "Axis_State": int(state),
        "Procedure_Result": result,
        "Trajectory_Done_Flag": int(done),
    }
    assert db.decode_message("Heartbeat", codec.encode_heartbeat(hb), decode_choices=False) == signals
    assert db.encode_message("Heartbeat", signals) == codec.encode_heartbeat(hb)


@given(finite_f32, finite_f32)
def test_dbc_estimates_both_ways(db: Any, pos: float, vel: float) -> None:
    data = codec.encode_encoder_estimates(codec.EncoderEstimates(pos, vel))
    assert db.decode_message(9, data) == {"Pos_Estimate": pos, "Vel_Estimate": vel}
    assert db.encode_message(9, {"Pos_Estimate": pos, "Vel_Estimate": vel}) == data


@given(finite_f32)
def test_dbc_torque_both_ways(db: Any, torque: float) -> None:
    data = codec.encode_set_input_torque(torque)
    assert db.decode_message(14, data) == {"Input_Torque": torque}
    assert db.encode_message(14, {"Input_Torque": torque}) == data


@pytest.mark.parametrize("state", list(AxisState))
def test_dbc_set_axis_state_both_ways(db: Any, state: AxisState) -> None:
    data = codec.encode_set_axis_state(state)
    assert db.decode_message(7, data, decode_choices=False) == {"Axis_Requested_State": int(state)}
    assert str(db.decode_message(7, data)["Axis_Requested_State"]) == state.name
    assert db.encode_message(7, {"Axis_Requested_State": int(state)}) == data
    assert codec.decode_set_axis_state(data) is state


@pytest.mark.parametrize("control", list(ControlMode))
@pytest.mark.parametrize("input_mode", list(InputMode))
def test_dbc_controller_mode_both_ways(db: Any, control: ControlMode, input_mode: InputMode) -> None:
    data = codec.encode_set_controller_mode(control, input_mode)
    decoded = db.decode_message(11, data)
    assert (str(decoded["Control_Mode"]), str(decoded["Input_Mode"])) == (control.name, input_mode.name)
    assert db.encode_message(11, {"Control_Mode": int(control), "Input_Mode": int(input_mode)}) == data
    assert codec.decode_set_controller_mode(data) == (control, input_mode)


def test_dbc_clear_errors_both_ways(db: Any) -> None:
    assert db.decode_message(24, codec.encode_clear_errors()) == {"Identify": 0}
    assert db.encode_message(24, {"Identify": 0}) == codec.encode_clear_errors()
    assert codec.decode_clear_errors(db.encode_message(24, {"Identify": 1})) == 1
