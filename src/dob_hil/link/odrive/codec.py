"""ODrive CANSimple: the frames a torque loop needs, as a pure codec (no I/O).

Follows ODrive firmware **0.6.x** (ODrive Pro, S1, Micro; docs.odriverobotics.com "CAN Protocol").
Every frame is a classic 11-bit data frame, ``arbitration id = node_id << 5 | cmd_id`` (node
0..63, command 0..31), little-endian signals, DLC 8 as in ODrive's published DBC:

==== ====================== ========= =====================================================
cmd  name                   direction payload
==== ====================== ========= =====================================================
0x01 Heartbeat              drive     u32 Axis_Error (ODriveError bits), u8 Axis_State,
                                      u8 Procedure_Result, u8 Trajectory_Done_Flag (bit 0)
0x07 Set_Axis_State         host      u32 Axis_Requested_State
0x09 Get_Encoder_Estimates  drive/RTR f32 Pos_Estimate [turns], f32 Vel_Estimate [turns/s]
0x0B Set_Controller_Mode    host      u32 Control_Mode, u32 Input_Mode
0x0E Set_Input_Torque       host      f32 Input_Torque [N m]
0x18 Clear_Errors           host      u8 Identify (0)
==== ====================== ========= =====================================================

Get_Encoder_Estimates is sent cyclically by the drive (``encoder_msg_rate_ms``) or on a remote
(RTR) request with the same id. Differences from firmware 0.5.x, which this module does not
speak: 0.5.x heartbeats carry error flags (motor/encoder/controller) in bytes 5..7 instead of
Procedure_Result, and the axis error bits differ (0.5.x WATCHDOG_TIMER_EXPIRED is 0x800; 0.6.x
reports ``active_errors`` where it is 0x1000000).

Decoders raise :class:`~dob_hil.errors.ProtocolError` naming the frame and what is wrong (short
payload, unknown state); they do not judge float values: :func:`decode_encoder_estimates`
returns NaN/inf as sent, and the link treats a non-finite estimate as a malformed frame.
"""

from __future__ import annotations

import enum
import math
import struct
from typing import Final, NamedTuple

from dob_hil.errors import ProtocolError

NODE_ID_MAX: Final = 63
CMD_ID_MASK: Final = 0x1F
DLC: Final = 8


class CmdId(enum.IntEnum):
    HEARTBEAT = 0x01
    SET_AXIS_STATE = 0x07
    GET_ENCODER_ESTIMATES = 0x09
    SET_CONTROLLER_MODE = 0x0B
    SET_INPUT_TORQUE = 0x0E
    CLEAR_ERRORS = 0x18


class AxisState(enum.IntEnum):
    UNDEFINED = 0
    IDLE = 1
    STARTUP_SEQUENCE = 2
    FULL_CALIBRATION_SEQUENCE = 3
    MOTOR_CALIBRATION = 4
    ENCODER_INDEX_SEARCH = 6
    ENCODER_OFFSET_CALIBRATION = 7
    CLOSED_LOOP_CONTROL = 8
    LOCKIN_SPIN = 9
    ENCODER_DIR_FIND = 10
    HOMING = 11
    ENCODER_HALL_POLARITY_CALIBRATION = 12
    ENCODER_HALL_PHASE_CALIBRATION = 13
    ANTICOGGING_CALIBRATION = 14


class ControlMode(enum.IntEnum):
    VOLTAGE_CONTROL = 0
    TORQUE_CONTROL = 1
    VELOCITY_CONTROL = 2
    POSITION_CONTROL = 3


class InputMode(enum.IntEnum):
    INACTIVE = 0
    PASSTHROUGH = 1
    VEL_RAMP = 2
    POS_FILTER = 3
    MIX_CHANNELS = 4
    TRAP_TRAJ = 5
    TORQUE_RAMP = 6
    MIRROR = 7
    TUNING = 8


class ODriveError(enum.IntFlag):
    """``axis.active_errors`` of firmware 0.6.x (the heartbeat's Axis_Error)."""

    INITIALIZING = 0x1
    SYSTEM_LEVEL = 0x2
    TIMING_ERROR = 0x4
    MISSING_ESTIMATE = 0x8
    BAD_CONFIG = 0x10
    DRV_FAULT = 0x20
    MISSING_INPUT = 0x40
    DC_BUS_OVER_VOLTAGE = 0x100
    DC_BUS_UNDER_VOLTAGE = 0x200
    DC_BUS_OVER_CURRENT = 0x400
    DC_BUS_OVER_REGEN_CURRENT = 0x800
    CURRENT_LIMIT_VIOLATION = 0x1000
    MOTOR_OVER_TEMP = 0x2000
    INVERTER_OVER_TEMP = 0x4000
    VELOCITY_LIMIT_VIOLATION = 0x8000
    POSITION_LIMIT_VIOLATION = 0x10000
    WATCHDOG_TIMER_EXPIRED = 0x1000000
    ESTOP_REQUESTED = 0x2000000
    SPINOUT_DETECTED = 0x4000000
    BRAKE_RESISTOR_DISARMED = 0x8000000
    THERMISTOR_DISCONNECTED = 0x10000000
    CALIBRATION_ERROR = 0x40000000


def error_names(bits: int) -> str:
    """``WATCHDOG_TIMER_EXPIRED|DRV_FAULT`` for the set bits (unknown ones as ``bit 0x...``); ``none``."""
    if bits == 0:
        return "none"
    names = []
    for bit in range(32):
        mask = 1 << bit
        if bits & mask:
            try:
                name = ODriveError(mask).name
            except ValueError:
                name = None
            names.append(name or f"bit 0x{mask:X}")
    return "|".join(names)


def arbitration_id(node_id: int, cmd: int) -> int:
    """``node_id << 5 | cmd``; ProtocolError for a node outside 0..63 or a command outside 0..31."""
    if isinstance(node_id, bool) or not isinstance(node_id, int) or not 0 <= node_id <= NODE_ID_MAX:
        raise ProtocolError(f"ODrive node id must be 0..{NODE_ID_MAX}, got {node_id!r}")
    if not 0 <= cmd <= CMD_ID_MASK:
        raise ProtocolError(f"ODrive command id must be 0..31, got {cmd!r}")
    return node_id << 5 | cmd


def split_id(arbitration_id: int) -> tuple[int, int]:
    """(node_id, cmd_id) of an 11-bit id."""
    return arbitration_id >> 5, arbitration_id & CMD_ID_MASK


class Heartbeat(NamedTuple):
    axis_error: int  # ODriveError bits
    axis_state: AxisState
    procedure_result: int = 0
    trajectory_done: bool = False


class EncoderEstimates(NamedTuple):
    pos_turns: float
    vel_turns_s: float


_HEARTBEAT: Final = struct.Struct("<IBBBx")
_U32_PAD: Final = struct.Struct("<I4x")
_TWO_U32: Final = struct.Struct("<II")
_TWO_F32: Final = struct.Struct("<ff")
_F32_PAD: Final = struct.Struct("<f4x")
_U8_PAD: Final = struct.Struct("<B7x")
F32_MAX: Final = 3.4028234663852886e38


def _need(data: bytes | bytearray, what: str) -> bytes:
    raw = bytes(data)
    if len(raw) != DLC:
        raise ProtocolError(f"{what}: expected {DLC} bytes, got {len(raw)}")
    return raw


def _f32(value: float, what: str) -> float:
    if not math.isfinite(value) or abs(value) > F32_MAX:
        raise ProtocolError(f"{what}: {value!r} is not a finite float32")
    return value


# --- Heartbeat (0x01) --------------------------------------------------------------------------
def encode_heartbeat(hb: Heartbeat) -> bytes:
    try:
        return _HEARTBEAT.pack(
            hb.axis_error, int(hb.axis_state), hb.procedure_result, int(hb.trajectory_done)
        )
    except struct.error as exc:
        raise ProtocolError(f"Heartbeat: {exc}") from None


def decode_heartbeat(data: bytes | bytearray) -> Heartbeat:
    error, state, result, done = _HEARTBEAT.unpack(_need(data, "Heartbeat"))
    try:
        axis_state = AxisState(state)
    except ValueError:
        raise ProtocolError(f"Heartbeat: unknown Axis_State {state}") from None
    return Heartbeat(error, axis_state, result, bool(done & 1))


# --- Set_Axis_State (0x07) ---------------------------------------------------------------------
def encode_set_axis_state(state: AxisState) -> bytes:
    return _U32_PAD.pack(int(state))


def decode_set_axis_state(data: bytes | bytearray) -> AxisState:
    (state,) = _U32_PAD.unpack(_need(data, "Set_Axis_State"))
    try:
        return AxisState(state)
    except ValueError:
        raise ProtocolError(f"Set_Axis_State: unknown Axis_Requested_State {state}") from None


# --- Get_Encoder_Estimates (0x09) --------------------------------------------------------------
def encode_encoder_estimates(est: EncoderEstimates) -> bytes:
    """Packs float32 as given (NaN and inf too: a drive may send them; the host refuses them)."""
    try:
        return _TWO_F32.pack(est.pos_turns, est.vel_turns_s)
    except (struct.error, OverflowError) as exc:
        raise ProtocolError(f"Get_Encoder_Estimates: {exc}") from None


def decode_encoder_estimates(data: bytes | bytearray) -> EncoderEstimates:
    pos, vel = _TWO_F32.unpack(_need(data, "Get_Encoder_Estimates"))
    return EncoderEstimates(pos, vel)


# --- Set_Controller_Mode (0x0B) ----------------------------------------------------------------
def encode_set_controller_mode(control: ControlMode, input_mode: InputMode) -> bytes:
    return _TWO_U32.pack(int(control), int(input_mode))


def decode_set_controller_mode(data: bytes | bytearray) -> tuple[ControlMode, InputMode]:
    control, input_mode = _TWO_U32.unpack(_need(data, "Set_Controller_Mode"))
    try:
        return ControlMode(control), InputMode(input_mode)
    except ValueError:
        raise ProtocolError(
            f"Set_Controller_Mode: unknown Control_Mode {control} or Input_Mode {input_mode}"
        ) from None


# --- Set_Input_Torque (0x0E) -------------------------------------------------------------------
def encode_set_input_torque(torque_Nm: float) -> bytes:
    """ProtocolError for a value that is not a finite float32 (never sent to a drive)."""
    return _F32_PAD.pack(_f32(torque_Nm, "Set_Input_Torque"))


def decode_set_input_torque(data: bytes | bytearray) -> float:
    (torque,) = _F32_PAD.unpack(_need(data, "Set_Input_Torque"))
    return float(torque)


# --- Clear_Errors (0x18) -----------------------------------------------------------------------
def encode_clear_errors(identify: int = 0) -> bytes:
    return _U8_PAD.pack(identify)


def decode_clear_errors(data: bytes | bytearray) -> int:
    (identify,) = _U8_PAD.unpack(_need(data, "Clear_Errors"))
    return int(identify)


def float32(value: float) -> float:
    """``value`` rounded to float32 (what the wire carries)."""
    return float(struct.unpack("<f", struct.pack("<f", value))[0])


def float32_bits(value: float) -> int:
    """The float32 bit pattern of ``value`` as a signed int32 (the ODrive profile's command code)."""
    return int(struct.unpack("<i", struct.pack("<f", value))[0])


def float32_from_bits(bits: int) -> float:
    return float(struct.unpack("<f", struct.pack("<i", bits))[0])
