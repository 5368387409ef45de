"""The CANopen CiA 301 / CiA 402 frames the host uses in the cyclic phase: a pure codec, no I/O.

Identifiers (CiA 301 predefined connection set, 11-bit): NMT 0x000, SYNC 0x080, EMCY 0x080 + node,
TPDO1 0x180 + node, RPDO1 0x200 + node, TPDO2 0x280 + node, SDO server->client 0x580 + node,
client->server 0x600 + node, heartbeat 0x700 + node.

Cyclic layout after the host's mapping (:mod:`dob_hil.link.cia402.link` maps it over SDO):

- RPDO1 (host -> drive), 4 bytes: controlword 0x6040 (u16), target torque 0x6071 (i16, per mille
  of rated torque 0x6076);
- TPDO1 (drive -> host), 6 bytes: statusword 0x6041 (u16), position actual value 0x6064 (i32,
  increments);
- TPDO2 (drive -> host, optional), 4 bytes: velocity actual value 0x606C (i32, increments/s).

All little endian (CiA 301 7.1). Controlword commands and statusword states are the tables of
CiA 402 (IEC 61800-7-201) section 6.2: each state is a (mask, value) of the low statusword bits.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass
from typing import Final

from dob_hil.errors import ProtocolError

NMT_ID: Final = 0x000
SYNC_ID: Final = 0x080
EMCY_BASE: Final = 0x080
TPDO1_BASE: Final = 0x180
RPDO1_BASE: Final = 0x200
TPDO2_BASE: Final = 0x280
SDO_TX_BASE: Final = 0x580  # server (drive) -> client (host)
SDO_RX_BASE: Final = 0x600  # client (host) -> server (drive)
HEARTBEAT_BASE: Final = 0x700

MODE_CYCLIC_SYNC_TORQUE: Final = 10  # 0x6060 / 0x6061 value of cyclic synchronous torque (CST)
SUPPORTED_MODE_CST_BIT: Final = 1 << 9  # 0x6502 supported drive modes: bit 9 = CST
DEVICE_PROFILE_402: Final = 402  # 0x1000 low 16 bits of a CiA 402 device
SYNC_COUNTER_MAX: Final = 240  # CiA 301: the SYNC counter runs 1..240 (0x1019 synchronous counter overflow)

# --- controlword 0x6040 (CiA 402 table 30: the device control commands) -----------------------------
CW_SWITCH_ON: Final = 1 << 0
CW_ENABLE_VOLTAGE: Final = 1 << 1
CW_QUICK_STOP: Final = 1 << 2  # active low: 0 requests a quick stop
CW_ENABLE_OPERATION: Final = 1 << 3
CW_FAULT_RESET: Final = 1 << 7  # acts on its rising edge


class Command(enum.Enum):
    """A device control command: (controlword, the transitions of CiA 402 figure 13 it causes).

    The word has only the bits the command sets (the mode-specific bits 4..6, 8 are 0)."""

    SHUTDOWN = (0x0006, "2, 6, 8")
    SWITCH_ON = (0x0007, "3")
    ENABLE_OPERATION = (0x000F, "4, 16")
    DISABLE_OPERATION = (0x0007, "5")
    DISABLE_VOLTAGE = (0x0000, "7, 9, 10, 12")
    QUICK_STOP = (0x0002, "7, 10, 11")
    FAULT_RESET = (0x0080, "15")

    @property
    def word(self) -> int:
        """The controlword value (u16)."""
        return self.value[0]


# --- statusword 0x6041 (CiA 402 table 32: the state coding) ---------------------------------------------
SW_READY_TO_SWITCH_ON: Final = 1 << 0
SW_SWITCHED_ON: Final = 1 << 1
SW_OPERATION_ENABLED: Final = 1 << 2
SW_FAULT: Final = 1 << 3
SW_VOLTAGE_ENABLED: Final = 1 << 4
SW_QUICK_STOP: Final = 1 << 5  # active low: 0 while a quick stop is active
SW_SWITCH_ON_DISABLED: Final = 1 << 6
SW_WARNING: Final = 1 << 7
SW_REMOTE: Final = 1 << 9
SW_TARGET_REACHED: Final = 1 << 10
SW_INTERNAL_LIMIT: Final = 1 << 11  # the drive limited the setpoint


class PowerState(enum.Enum):
    """The CiA 402 power drive system states, each ``(mask, value)`` of the statusword."""

    NOT_READY_TO_SWITCH_ON = (0x004F, 0x0000)
    SWITCH_ON_DISABLED = (0x004F, 0x0040)
    READY_TO_SWITCH_ON = (0x006F, 0x0021)
    SWITCHED_ON = (0x006F, 0x0023)
    OPERATION_ENABLED = (0x006F, 0x0027)
    QUICK_STOP_ACTIVE = (0x006F, 0x0007)
    FAULT_REACTION_ACTIVE = (0x004F, 0x000F)
    FAULT = (0x004F, 0x0008)

    @property
    def mask(self) -> int:
        return self.value[0]

    @property
    def pattern(self) -> int:
        return self.value[1]


def _state_of(low_bits: int) -> PowerState | None:
    for state in PowerState:
        if low_bits & state.mask == state.pattern:
            return state
    return None


_STATE_MASK: Final = 0x006F  # every state's mask is within these bits
_STATE_TABLE: Final = tuple(_state_of(bits) for bits in range(_STATE_MASK + 1))


def decode_state(statusword: int) -> PowerState | None:
    """The state a statusword codes, or None for a combination the standard does not define."""
    return _STATE_TABLE[statusword & _STATE_MASK]


# the command that moves each state one step towards OPERATION_ENABLED (CiA 402 figure 13);
# FAULT needs the rising edge of bit 7: send a word with bit 7 clear first (see fault_reset_words)
_TOWARDS_ENABLED: Final[dict[PowerState, Command]] = {
    PowerState.SWITCH_ON_DISABLED: Command.SHUTDOWN,  # transition 2
    PowerState.READY_TO_SWITCH_ON: Command.SWITCH_ON,  # transition 3
    PowerState.SWITCHED_ON: Command.ENABLE_OPERATION,  # transition 4
    PowerState.QUICK_STOP_ACTIVE: Command.DISABLE_VOLTAGE,  # transition 12
    PowerState.FAULT: Command.FAULT_RESET,  # transition 15
}


def command_towards_enabled(state: PowerState) -> Command | None:
    """The next command on the way to OPERATION_ENABLED; None where the drive moves on its own
    (NOT_READY_TO_SWITCH_ON, FAULT_REACTION_ACTIVE) or is there already."""
    return _TOWARDS_ENABLED.get(state)


def fault_reset_words() -> tuple[int, int]:
    """The two controlwords of a fault reset: bit 7 clear, then set (the rising edge)."""
    return Command.DISABLE_VOLTAGE.word, Command.FAULT_RESET.word


# --- NMT, SYNC, heartbeat ------------------------------------------------------------------------------
class NmtCommand(enum.IntEnum):
    """CiA 301 NMT command specifiers (byte 0 of the NMT frame)."""

    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(enum.IntEnum):
    """CiA 301 heartbeat states."""

    BOOT_UP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


def encode_nmt(command: NmtCommand, node_id: int) -> bytes:
    """The 2-byte NMT frame (id 0x000); ``node_id`` 0 addresses every node."""
    if not 0 <= node_id <= 127:
        raise ProtocolError(f"NMT: node id must be 0..127, got {node_id}")
    return bytes((int(command), node_id))


def encode_sync(counter: int | None = None) -> bytes:
    """The SYNC payload: empty, or the 1-byte counter 1..240 (when 0x1019 > 0)."""
    if counter is None:
        return b""
    if not 1 <= counter <= SYNC_COUNTER_MAX:
        raise ProtocolError(f"SYNC: the counter runs 1..{SYNC_COUNTER_MAX}, got {counter}")
    return bytes((counter,))


def decode_heartbeat(data: bytes | bytearray) -> NmtState:
    """The NMT state of a heartbeat (bit 7 is the node-guarding toggle; ignored)."""
    if len(data) != 1:
        raise ProtocolError(f"heartbeat: expected 1 byte, got {len(data)}")
    try:
        return NmtState(data[0] & 0x7F)
    except ValueError:
        raise ProtocolError(f"heartbeat: 0x{data[0]:02X} is no NMT state") from None


# --- EMCY -------------------------------------------------------------------------------------------------
_EMCY: Final = struct.Struct("<HB5s")

# CiA 301 table 21 (error code classes) and the codes a CiA 402 servo drive commonly sends
EMCY_CLASSES: Final[dict[int, str]] = {
    0x00: "error reset or no error",
    0x10: "generic error",
    0x20: "current",
    0x21: "current, device input side",
    0x22: "current inside the device",
    0x23: "current, device output side",
    0x30: "voltage",
    0x31: "mains voltage",
    0x32: "voltage inside the device",
    0x33: "output voltage",
    0x40: "temperature",
    0x41: "ambient temperature",
    0x42: "device temperature",
    0x50: "device hardware",
    0x60: "device software",
    0x61: "internal software",
    0x62: "user software",
    0x63: "data set",
    0x70: "additional modules",
    0x71: "motor",
    0x73: "sensor",
    0x80: "monitoring",
    0x81: "communication",
    0x82: "protocol error",
    0x86: "control",
    0x90: "external error",
    0xF0: "additional functions",
    0xFF: "device specific",
}
EMCY_CODES: Final[dict[int, str]] = {
    0x0000: "error reset or no error",
    0x2310: "continuous over current",
    0x3210: "DC link over voltage",
    0x3220: "DC link under voltage",
    0x4310: "drive temperature too high",
    0x7305: "incremental sensor 1 fault",
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard or heartbeat error",
    0x8140: "recovered from bus off",
    0x8210: "PDO not processed due to length error",
    0x8220: "PDO length exceeded",
    0x8240: "unexpected SYNC data length",
    0x8250: "RPDO timeout",
    0x8611: "following error",
    0x8700: "SYNC controller error (SYNC lost)",
}


@dataclass(frozen=True, slots=True)
class Emcy:
    """One EMCY frame: error code (CiA 301/402), error register 0x1001, manufacturer bytes."""

    error_code: int
    error_register: int
    manufacturer: bytes = bytes(5)

    @property
    def is_reset(self) -> bool:
        """Code 0x0000: the drive left its error state (or has none)."""
        return self.error_code == 0

    def describe(self) -> str:
        """``0x8250 (RPDO timeout), register 0x11``."""
        meaning = EMCY_CODES.get(self.error_code) or EMCY_CLASSES.get(self.error_code >> 8)
        if meaning is None:
            meaning = EMCY_CLASSES.get((self.error_code >> 8) & 0xF0, "unknown class")
        return f"0x{self.error_code:04X} ({meaning}), register 0x{self.error_register:02X}"


def encode_emcy(emcy: Emcy) -> bytes:
    if len(emcy.manufacturer) != 5:
        raise ProtocolError(f"EMCY: 5 manufacturer bytes, got {len(emcy.manufacturer)}")
    return _EMCY.pack(emcy.error_code, emcy.error_register, emcy.manufacturer)


def decode_emcy(data: bytes | bytearray) -> Emcy:
    """An 8-byte EMCY payload: error code (u16), error register (u8), 5 manufacturer bytes."""
    if len(data) != _EMCY.size:
        raise ProtocolError(f"EMCY: expected 8 bytes, got {len(data)}")
    code, register, manufacturer = _EMCY.unpack(data)
    return Emcy(code, register, manufacturer)


# --- the cyclic PDOs ---------------------------------------------------------------------------------------
RPDO1: Final = struct.Struct("<Hh")  # controlword 0x6040, target torque 0x6071
TPDO1: Final = struct.Struct("<Hi")  # statusword 0x6041, position actual value 0x6064
TPDO2: Final = struct.Struct("<i")  # velocity actual value 0x606C
RPDO1_MAP: Final = ((0x6040, 0, 16), (0x6071, 0, 16))  # (index, subindex, bits) as mapped
TPDO1_MAP: Final = ((0x6041, 0, 16), (0x6064, 0, 32))
TPDO2_MAP: Final = ((0x606C, 0, 32),)
TORQUE_PERMILLE_MAX: Final = 32767  # the i16 range of 0x6071


def encode_rpdo1(controlword: int, target_torque_permille: int) -> bytes:
    """RPDO1: controlword (u16) and target torque in per mille of rated torque (i16)."""
    try:
        return RPDO1.pack(controlword, target_torque_permille)
    except struct.error:
        raise ProtocolError(
            f"RPDO1: controlword 0..0xFFFF and target torque -32768..32767, got "
            f"{controlword!r} and {target_torque_permille!r}"
        ) from None


def decode_rpdo1(data: bytes | bytearray) -> tuple[int, int]:
    if len(data) != RPDO1.size:
        raise ProtocolError(f"RPDO1: expected {RPDO1.size} bytes, got {len(data)}")
    cw, torque = RPDO1.unpack(data)
    return int(cw), int(torque)


def encode_tpdo1(statusword: int, position_counts: int) -> bytes:
    try:
        return TPDO1.pack(statusword, position_counts)
    except struct.error:
        raise ProtocolError(
            f"TPDO1: statusword u16 and position i32, got {statusword!r}, {position_counts!r}"
        ) from None


def decode_tpdo1(data: bytes | bytearray) -> tuple[int, int]:
    """(statusword, position actual value in increments)."""
    if len(data) != TPDO1.size:
        raise ProtocolError(f"TPDO1: expected {TPDO1.size} bytes, got {len(data)}")
    sw, pos = TPDO1.unpack(data)
    return int(sw), int(pos)


def decode_tpdo2(data: bytes | bytearray) -> int:
    """Velocity actual value in increments per second."""
    if len(data) != TPDO2.size:
        raise ProtocolError(f"TPDO2: expected {TPDO2.size} bytes, got {len(data)}")
    return int(TPDO2.unpack(data)[0])


def cob_ids(node_id: int) -> dict[str, int]:
    """The COB-IDs of one node (CiA 301 predefined connection set)."""
    if not 1 <= node_id <= 127:
        raise ProtocolError(f"a CANopen node id is 1..127, got {node_id}")
    return {
        "EMCY": EMCY_BASE + node_id,
        "TPDO1": TPDO1_BASE + node_id,
        "RPDO1": RPDO1_BASE + node_id,
        "TPDO2": TPDO2_BASE + node_id,
        "SDO_TX": SDO_TX_BASE + node_id,
        "SDO_RX": SDO_RX_BASE + node_id,
        "HEARTBEAT": HEARTBEAT_BASE + node_id,
    }
