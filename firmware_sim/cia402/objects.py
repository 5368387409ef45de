"""Object indices, EMCY and SDO abort codes of the simulated CiA 402 drive, and its shipped EDS."""

from __future__ import annotations

import importlib.resources
from pathlib import Path

# --- CiA 301 communication objects -------------------------------------------------------------
ERROR_REGISTER = 0x1001
ERROR_HISTORY = 0x1003
COB_ID_SYNC = 0x1005
CYCLE_PERIOD = 0x1006  # microseconds
HEARTBEAT_PRODUCER = 0x1017  # milliseconds
COB_ID_EMCY = 0x1014
SYNC_OVERFLOW = 0x1019
RPDO_COMM, RPDO_MAP = 0x1400, 0x1600
TPDO_COMM, TPDO_MAP = 0x1800, 0x1A00
N_PDO = 4

# --- CiA 402 drive objects ---------------------------------------------------------------------
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION = 0x605A
MODES_OF_OPERATION = 0x6060
MODES_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064  # increments (int32)
VELOCITY_ACTUAL = 0x606C  # increments per second (int32)
TARGET_TORQUE = 0x6071  # per mille of rated torque (int16)
MAX_TORQUE = 0x6072  # per mille of rated torque (uint16)
RATED_CURRENT = 0x6075  # mA
RATED_TORQUE = 0x6076  # mN m
TORQUE_ACTUAL = 0x6077  # per mille of rated torque
CURRENT_ACTUAL = 0x6078  # per mille of rated current
ENCODER_RESOLUTION = 0x608F  # sub 1 increments per sub 2 revolutions

MODE_NONE = 0
MODE_CST = 10  # cyclic synchronous torque
SUPPORTED_MODES = frozenset({MODE_NONE, MODE_CST})

# --- EMCY error codes (CiA 301 / CiA 402) and error register bits ------------------------------
EMCY_NO_ERROR = 0x0000  # error reset
EMCY_OVERCURRENT = 0x2310  # continuous over current (the injected [sim.faults] fault)
EMCY_ENCODER = 0x7305  # incremental sensor 1 fault (the plant position is not finite)
EMCY_COMMUNICATION = 0x8100  # communication, generic: SYNC lost, NMT left OPERATIONAL while enabled
EMCY_PDO_LENGTH = 0x8210  # PDO not processed due to length error
EMCY_PDO_LENGTH_EXCEEDED = 0x8220  # PDO length exceeded (processed)
EMCY_SYNC_LENGTH = 0x8240  # unexpected SYNC data length
EMCY_RPDO_TIMEOUT = 0x8250  # RPDO timeout

ER_GENERIC = 0x01
ER_CURRENT = 0x02
ER_COMMUNICATION = 0x10

FAULT_REGISTER = {
    EMCY_OVERCURRENT: ER_GENERIC | ER_CURRENT,
    EMCY_ENCODER: ER_GENERIC,
    EMCY_COMMUNICATION: ER_GENERIC | ER_COMMUNICATION,
    EMCY_RPDO_TIMEOUT: ER_GENERIC | ER_COMMUNICATION,
}

# --- SDO abort codes (CiA 301) -----------------------------------------------------------------
ABORT_INVALID_COMMAND = 0x05040001
ABORT_UNSUPPORTED_ACCESS = 0x06010000
ABORT_NOT_IN_OD = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_INVALID_VALUE = 0x06090030
ABORT_VALUE_TOO_HIGH = 0x06090031
ABORT_DEVICE_STATE = 0x08000022

PDO_INVALID = 1 << 31
PDO_NO_RTR = 1 << 30
PDO_EXTENDED = 1 << 29


def shipped_eds() -> Path:
    """The generic CiA 402 EDS shipped with dob_hil: this drive's object dictionary."""
    return Path(str(importlib.resources.files("dob_hil.link") / "cia402" / "generic_cia402.eds"))
