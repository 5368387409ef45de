"""The native drive protocol, version 2: a pure codec (bytes in, values out), shared by host and drive.

Classic CAN 2.0A (11-bit ids), little endian. ``docs/PROTOCOL.md`` is the behavioural contract
(who sends what when, validity, the watchdog, the handshakes); ``dob_hil/link/native.dbc`` the
same frames for CAN tools (node 1). An id is ``function base + node_id`` with node 0..15; every
id lies in 0x680..0x6CF, a range CANopen's predefined connection set (CiA 301: EMCY/SYNC 0x080,
PDOs 0x180..0x57F, SDO 0x580/0x600, NMT error control 0x700) leaves free, so the native
protocol shares a bus with CANopen (CiA 402) nodes without a clash.

======================  ======  ===  ==========================================================
frame                   id      len  payload (little endian)
======================  ======  ===  ==========================================================
FAULT (drive->host)     0x680+n  2   u8 fault code, u8 info
CONTROL (host->drive)   0x690+n  2   u8 request: 0 disable, 1 enable, 2 clear fault; u8 version
COMMAND (host->drive)   0x6A0+n  3   i16 current in DAC counts, u8: bits 0-6 the feedback
                                     sequence answered (mod 128), bit 7 enable
FEEDBACK (drive->host)  0x6B0+n  6   i32 encoder counts (wrapping), u8 sequence, u8 status bits
HEARTBEAT (drive->host) 0x6C0+n  2   u8 drive state: 0 disabled, 1 enabled, 2 fault; u8 version
======================  ======  ===  ==========================================================

Lengths: a sender sends exactly ``len`` bytes; a receiver accepts a frame padded up to 8 bytes
(any padding value, ignored) and rejects a shorter one. Version: CONTROL and HEARTBEAT carry
:data:`PROTOCOL_VERSION`; :func:`decode` returns what came, the peers compare (PROTOCOL.md).

Out-of-range policy: ``encode_*`` raises :class:`ProtocolError` naming the signal, its limits
and the value; clamping to a limit is the separate, named step :func:`saturate_current_counts`.
``decode_*`` checks the length and the reserved bits and raises :class:`ProtocolError` naming the
frame, what was expected and what came.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

from dob_hil.errors import ProtocolError

PROTOCOL_VERSION: Final = 2  # carried by CONTROL and HEARTBEAT; see PROTOCOL.md "Version"
NODE_ID_MAX: Final = 15
ID_FIRST: Final = 0x680  # every native id lies in ID_FIRST..ID_LAST
ID_LAST: Final = 0x6CF
MAX_PADDED_LEN: Final = 8  # a receiver accepts frames padded up to this many bytes
HEARTBEAT_PERIOD_NS: Final = 100_000_000  # the drive sends a HEARTBEAT at least this often
SEQ_MODULO: Final = 256  # feedback sequence counter
COMMAND_SEQ_MODULO: Final = 128  # the command carries the answered sequence mod 128
CURRENT_COUNTS_MIN: Final = -32768
CURRENT_COUNTS_MAX: Final = 32767
COUNTS_MIN: Final = -(2**31)
COUNTS_MAX: Final = 2**31 - 1


class FrameKind(enum.IntEnum):
    """Function base of each frame; the id on the bus is ``base + node_id``."""

    FAULT = 0x680
    CONTROL = 0x690
    COMMAND = 0x6A0
    FEEDBACK = 0x6B0
    HEARTBEAT = 0x6C0


DLC: Final[dict[FrameKind, int]] = {  # the length a sender sends (a receiver accepts up to 8)
    FrameKind.FAULT: 2,
    FrameKind.CONTROL: 2,
    FrameKind.COMMAND: 3,
    FrameKind.FEEDBACK: 6,
    FrameKind.HEARTBEAT: 2,
}


class Status(enum.IntFlag):
    """Status bits of the feedback frame."""

    ENABLED = 0x01
    FAULT = 0x02
    SATURATED = 0x04  # the drive clamped the last command at its current limit
    WATCHDOG = 0x08  # the last fault was the command watchdog


STATUS_RESERVED_MASK: Final = 0xF0


class ControlRequest(enum.IntEnum):
    DISABLE = 0
    ENABLE = 1
    CLEAR_FAULT = 2


class DriveState(enum.IntEnum):
    DISABLED = 0
    ENABLED = 1
    FAULT = 2


class FaultCode(enum.IntEnum):
    """Why the drive entered FAULT (PROTOCOL.md "Faults" says what raises each)."""

    WATCHDOG = 1  # info: periods without a valid command (capped at 255); 0: no first command
    OVERCURRENT = 2  # info: 0
    ENCODER = 3  # info: 0 (the position cannot be measured or represented)
    BAD_FRAME = 4  # info: the low byte of the offending id
    COMMAND_WHILE_DISABLED = 5  # info: 0 (optional: a COMMAND while DISABLED)
    HOST_REQUEST = 6  # info: 0 (the host asked for a fault stop)


@dataclass(frozen=True, slots=True)
class FeedbackFrame:
    counts: int  # raw encoder counter, wraps at the configured width
    seq: int  # 0..255
    status: Status


@dataclass(frozen=True, slots=True)
class CommandFrame:
    current_counts: int  # DAC counts, int16
    seq: int  # the feedback sequence answered, 0..127 (mod 128)
    enable: bool


@dataclass(frozen=True, slots=True)
class ControlFrame:
    request: ControlRequest
    version: int = PROTOCOL_VERSION  # the protocol version the host speaks


@dataclass(frozen=True, slots=True)
class FaultFrame:
    code: FaultCode
    info: int  # 0..255


@dataclass(frozen=True, slots=True)
class HeartbeatFrame:
    state: DriveState
    version: int = PROTOCOL_VERSION  # the protocol version the drive speaks


Frame = FeedbackFrame | CommandFrame | ControlFrame | FaultFrame | HeartbeatFrame

_FEEDBACK: Final = struct.Struct("<iBB")
_COMMAND: Final = struct.Struct("<hB")
_TWO_U8: Final = struct.Struct("<BB")


def frame_id(kind: FrameKind, node_id: int) -> int:
    """The 11-bit arbitration id of ``kind`` for ``node_id``."""
    if isinstance(node_id, bool) or not isinstance(node_id, int) or not 0 <= node_id <= NODE_ID_MAX:
        raise ProtocolError(f"node_id: the native protocol has nodes 0..{NODE_ID_MAX}, got {node_id}")
    return int(kind) + node_id


def split_id(arbitration_id: int) -> tuple[FrameKind, int]:
    """(kind, node_id) of an 11-bit id; :class:`ProtocolError` for an id of no native frame."""
    base, node = arbitration_id & 0x7F0, arbitration_id & 0x00F
    if not 0 <= arbitration_id <= 0x7FF:
        raise ProtocolError(f"id 0x{arbitration_id:X}: not an 11-bit id")
    try:
        return FrameKind(base), node
    except ValueError:
        raise ProtocolError(f"id 0x{arbitration_id:03X}: not a frame of the native protocol") from None


def _check(signal: str, value: int, low: int, high: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ProtocolError(f"{signal}: expected an integer, got {value!r}")
    if not low <= value <= high:
        raise ProtocolError(f"{signal}: {value} is outside {low}..{high}")


def _check_code(signal: str, value: int, codes: type[enum.IntEnum]) -> int:
    """``value`` as a plain int if it is one of ``codes``; else :class:`ProtocolError` naming the set."""
    valid = ", ".join(f"{member.value} ({member.name})" for member in codes)
    if isinstance(value, bool) or not isinstance(value, int):
        raise ProtocolError(f"{signal}: expected an integer code, got {value!r}; valid: {valid}")
    try:
        return int(codes(value))
    except ValueError:
        raise ProtocolError(f"{signal}: {value} is not a valid code; valid: {valid}") from None


def _check_len(kind: FrameKind, data: bytes | bytearray | memoryview) -> None:
    """A frame of ``kind`` is its length, or padded up to 8 bytes; anything else is malformed."""
    if not DLC[kind] <= len(data) <= MAX_PADDED_LEN:
        raise ProtocolError(
            f"{kind.name} frame: expected {DLC[kind]} bytes (padding up to {MAX_PADDED_LEN} allowed), "
            f"got {len(data)} byte(s) {bytes(data).hex() or '-'}"
        )


# --- saturation: a separate, named step --------------------------------------------------------
def saturate_current_counts(current_counts: int, limit_counts: int) -> int:
    """Clamp a DAC code to ``[-limit_counts, +limit_counts]``."""
    if current_counts > limit_counts:
        return limit_counts
    if current_counts < -limit_counts:
        return -limit_counts
    return current_counts


# --- FEEDBACK -------------------------------------------------------------------------------------
def encode_feedback(frame: FeedbackFrame) -> bytes:
    _check("FEEDBACK.counts", frame.counts, COUNTS_MIN, COUNTS_MAX)
    _check("FEEDBACK.seq", frame.seq, 0, SEQ_MODULO - 1)
    _check("FEEDBACK.status", frame.status, 0, 0x0F)
    return _FEEDBACK.pack(frame.counts, frame.seq, int(frame.status))


def decode_feedback(data: bytes | bytearray | memoryview) -> FeedbackFrame:
    _check_len(FrameKind.FEEDBACK, data)
    counts, seq, status = _FEEDBACK.unpack_from(data)
    if status & STATUS_RESERVED_MASK:
        raise ProtocolError(f"FEEDBACK frame: reserved status bits set (0x{status:02X})")
    return FeedbackFrame(counts, seq, Status(status))


# --- COMMAND --------------------------------------------------------------------------------------
def encode_command(frame: CommandFrame) -> bytes:
    _check("COMMAND.current_counts", frame.current_counts, CURRENT_COUNTS_MIN, CURRENT_COUNTS_MAX)
    _check("COMMAND.seq", frame.seq, 0, COMMAND_SEQ_MODULO - 1)
    return _COMMAND.pack(frame.current_counts, frame.seq | (0x80 if frame.enable else 0))


def decode_command(data: bytes | bytearray | memoryview) -> CommandFrame:
    _check_len(FrameKind.COMMAND, data)
    current, tail = _COMMAND.unpack_from(data)
    return CommandFrame(current, tail & 0x7F, bool(tail & 0x80))


# --- CONTROL, FAULT, HEARTBEAT ---------------------------------------------------------------------
def encode_control(frame: ControlFrame) -> bytes:
    _check("CONTROL.version", frame.version, 0, 255)
    return bytes((_check_code("CONTROL.request", frame.request, ControlRequest), frame.version))


def decode_control(data: bytes | bytearray | memoryview) -> ControlFrame:
    """The request and the version as sent; the version is compared by the drive, not here."""
    _check_len(FrameKind.CONTROL, data)
    try:
        return ControlFrame(ControlRequest(data[0]), data[1])
    except ValueError:
        raise ProtocolError(f"CONTROL frame: unknown request {data[0]}") from None


def encode_fault(frame: FaultFrame) -> bytes:
    code = _check_code("FAULT.code", frame.code, FaultCode)
    _check("FAULT.info", frame.info, 0, 255)
    return _TWO_U8.pack(code, frame.info)


def decode_fault(data: bytes | bytearray | memoryview) -> FaultFrame:
    _check_len(FrameKind.FAULT, data)
    code, info = _TWO_U8.unpack_from(data)
    try:
        return FaultFrame(FaultCode(code), info)
    except ValueError:
        raise ProtocolError(f"FAULT frame: unknown fault code {code}") from None


def encode_heartbeat(frame: HeartbeatFrame) -> bytes:
    _check("HEARTBEAT.version", frame.version, 0, 255)
    return bytes((_check_code("HEARTBEAT.state", frame.state, DriveState), frame.version))


def decode_heartbeat(data: bytes | bytearray | memoryview) -> HeartbeatFrame:
    """The state and the version as sent; the version is compared by the host, not here."""
    _check_len(FrameKind.HEARTBEAT, data)
    try:
        return HeartbeatFrame(DriveState(data[0]), data[1])
    except ValueError:
        raise ProtocolError(f"HEARTBEAT frame: unknown drive state {data[0]}") from None


_DECODERS: Final[dict[FrameKind, Callable[[bytes | bytearray | memoryview], Frame]]] = {
    FrameKind.FAULT: decode_fault,
    FrameKind.FEEDBACK: decode_feedback,
    FrameKind.COMMAND: decode_command,
    FrameKind.CONTROL: decode_control,
    FrameKind.HEARTBEAT: decode_heartbeat,
}


def encode(frame: Frame) -> tuple[FrameKind, bytes]:
    """Any native frame to (kind, payload)."""
    if isinstance(frame, FeedbackFrame):
        return FrameKind.FEEDBACK, encode_feedback(frame)
    if isinstance(frame, CommandFrame):
        return FrameKind.COMMAND, encode_command(frame)
    if isinstance(frame, ControlFrame):
        return FrameKind.CONTROL, encode_control(frame)
    if isinstance(frame, FaultFrame):
        return FrameKind.FAULT, encode_fault(frame)
    return FrameKind.HEARTBEAT, encode_heartbeat(frame)


def decode(arbitration_id: int, data: bytes | bytearray | memoryview) -> tuple[int, Frame]:
    """(node_id, frame) of a raw frame; :class:`ProtocolError` naming what was wrong."""
    kind, node = split_id(arbitration_id)
    return node, _DECODERS[kind](data)


def seq_answers(command_seq: int, feedback_seq: int) -> bool:
    """True if a command's 7-bit sequence answers the 8-bit feedback sequence."""
    return command_seq == feedback_seq % COMMAND_SEQ_MODULO
