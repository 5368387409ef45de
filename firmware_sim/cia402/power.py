"""The CiA 402 power state machine (device control): controlword in, state and statusword out.

Pure logic, no I/O. States and statusword patterns (CiA 402-2, the ``x`` bits are not part of
the pattern)::

    NOT READY TO SWITCH ON   xxxx xxxx x0xx 0000
    SWITCH ON DISABLED       xxxx xxxx x1xx 0000
    READY TO SWITCH ON       xxxx xxxx x01x 0001
    SWITCHED ON              xxxx xxxx x01x 0011
    OPERATION ENABLED        xxxx xxxx x01x 0111
    QUICK STOP ACTIVE        xxxx xxxx x00x 0111
    FAULT REACTION ACTIVE    xxxx xxxx x0xx 1111
    FAULT                    xxxx xxxx x0xx 1000

Controlword commands (bit 7 clear): shutdown ``0xxx x110``, switch on ``0xxx 0111``, switch on +
enable operation ``0xxx 1111``, disable voltage ``0xxx xx0x``, quick stop ``0xxx x01x``, disable
operation ``0xxx 0111``, enable operation ``0xxx 1111``; fault reset on a rising edge of bit 7.
While bit 7 is set no other command is taken. Quick stop option code (0x605A) 5..8 stays in
QUICK STOP ACTIVE (transition 16 back to OPERATION ENABLED allowed); any other code leaves it for
SWITCH ON DISABLED at the next SYNC (:meth:`PowerStateMachine.on_sync`), the torque being zero
from the quick stop on.
"""

from __future__ import annotations

import enum

CW_SWITCH_ON = 0x0001
CW_ENABLE_VOLTAGE = 0x0002
CW_QUICK_STOP = 0x0004  # active low: 0 commands a quick stop
CW_ENABLE_OPERATION = 0x0008
CW_FAULT_RESET = 0x0080
CW_HALT = 0x0100

SW_READY_TO_SWITCH_ON = 0x0001
SW_SWITCHED_ON = 0x0002
SW_OPERATION_ENABLED = 0x0004
SW_FAULT = 0x0008
SW_VOLTAGE_ENABLED = 0x0010
SW_QUICK_STOP = 0x0020  # active low: 0 while a quick stop is active
SW_SWITCH_ON_DISABLED = 0x0040
SW_REMOTE = 0x0200
SW_INTERNAL_LIMIT = 0x0800
SW_FOLLOWS_COMMAND = 0x1000  # cyclic synchronous modes: the drive follows the command value

QUICK_STOP_STAYS = frozenset({5, 6, 7, 8})  # 0x605A codes that stay in QUICK STOP ACTIVE


class PowerState(enum.Enum):
    NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
    SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
    READY_TO_SWITCH_ON = "READY TO SWITCH ON"
    SWITCHED_ON = "SWITCHED ON"
    OPERATION_ENABLED = "OPERATION ENABLED"
    QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
    FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
    FAULT = "FAULT"


STATUS_BITS: dict[PowerState, int] = {
    PowerState.NOT_READY_TO_SWITCH_ON: 0x0000,
    PowerState.SWITCH_ON_DISABLED: SW_SWITCH_ON_DISABLED,
    PowerState.READY_TO_SWITCH_ON: SW_QUICK_STOP | SW_READY_TO_SWITCH_ON,
    PowerState.SWITCHED_ON: SW_QUICK_STOP | SW_VOLTAGE_ENABLED | SW_SWITCHED_ON | SW_READY_TO_SWITCH_ON,
    PowerState.OPERATION_ENABLED: SW_QUICK_STOP
    | SW_VOLTAGE_ENABLED
    | SW_OPERATION_ENABLED
    | SW_SWITCHED_ON
    | SW_READY_TO_SWITCH_ON,
    PowerState.QUICK_STOP_ACTIVE: SW_VOLTAGE_ENABLED
    | SW_OPERATION_ENABLED
    | SW_SWITCHED_ON
    | SW_READY_TO_SWITCH_ON,
    PowerState.FAULT_REACTION_ACTIVE: SW_VOLTAGE_ENABLED
    | SW_FAULT
    | SW_OPERATION_ENABLED
    | SW_SWITCHED_ON
    | SW_READY_TO_SWITCH_ON,
    PowerState.FAULT: SW_FAULT,
}

_S = PowerState


def _command(cw: int) -> str:
    """The device control command a controlword (bit 7 clear) encodes."""
    if not cw & CW_ENABLE_VOLTAGE:
        return "disable_voltage"
    if not cw & CW_QUICK_STOP:
        return "quick_stop"
    if not cw & CW_SWITCH_ON:
        return "shutdown"
    if cw & CW_ENABLE_OPERATION:
        return "enable_operation"  # also "switch on + enable operation"
    return "switch_on"  # also "disable operation"


# (state, command) -> next state; absent pairs leave the state unchanged
_TRANSITIONS: dict[tuple[PowerState, str], PowerState] = {
    (_S.SWITCH_ON_DISABLED, "shutdown"): _S.READY_TO_SWITCH_ON,  # 2
    (_S.READY_TO_SWITCH_ON, "switch_on"): _S.SWITCHED_ON,  # 3
    (_S.READY_TO_SWITCH_ON, "enable_operation"): _S.OPERATION_ENABLED,  # 3 + 4
    (_S.READY_TO_SWITCH_ON, "disable_voltage"): _S.SWITCH_ON_DISABLED,  # 7
    (_S.READY_TO_SWITCH_ON, "quick_stop"): _S.SWITCH_ON_DISABLED,  # 7
    (_S.SWITCHED_ON, "enable_operation"): _S.OPERATION_ENABLED,  # 4
    (_S.SWITCHED_ON, "shutdown"): _S.READY_TO_SWITCH_ON,  # 6
    (_S.SWITCHED_ON, "disable_voltage"): _S.SWITCH_ON_DISABLED,  # 10
    (_S.SWITCHED_ON, "quick_stop"): _S.SWITCH_ON_DISABLED,  # 10
    (_S.OPERATION_ENABLED, "switch_on"): _S.SWITCHED_ON,  # 5
    (_S.OPERATION_ENABLED, "shutdown"): _S.READY_TO_SWITCH_ON,  # 8
    (_S.OPERATION_ENABLED, "disable_voltage"): _S.SWITCH_ON_DISABLED,  # 9
    (_S.OPERATION_ENABLED, "quick_stop"): _S.QUICK_STOP_ACTIVE,  # 11
    (_S.QUICK_STOP_ACTIVE, "disable_voltage"): _S.SWITCH_ON_DISABLED,  # 12
}


class PowerStateMachine:
    """The drive's device-control state; the caller zeroes the torque when :attr:`torque_allowed` drops."""

    def __init__(self) -> None:
        self.state = PowerState.NOT_READY_TO_SWITCH_ON
        self.controlword = 0  # the last controlword taken
        self.quick_stop_option = 2  # 0x605A

    def boot(self) -> None:
        """Initialisation done: NOT READY TO SWITCH ON, then SWITCH ON DISABLED (transition 0, 1)."""
        self.state = PowerState.SWITCH_ON_DISABLED
        self.controlword = 0

    @property
    def torque_allowed(self) -> bool:
        return self.state is PowerState.OPERATION_ENABLED

    @property
    def statusword_bits(self) -> int:
        return STATUS_BITS[self.state] | SW_REMOTE

    def apply(self, controlword: int) -> PowerState:
        """Take a controlword; returns the new state."""
        rising_reset = bool(controlword & CW_FAULT_RESET) and not self.controlword & CW_FAULT_RESET
        self.controlword = controlword & 0xFFFF
        s = self.state
        if controlword & CW_FAULT_RESET:
            if rising_reset and s is PowerState.FAULT:
                self.state = PowerState.SWITCH_ON_DISABLED  # 15
            return self.state
        if s in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE, PowerState.NOT_READY_TO_SWITCH_ON):
            return s
        cmd = _command(controlword)
        if s is PowerState.QUICK_STOP_ACTIVE and cmd == "enable_operation":
            if self.quick_stop_option in QUICK_STOP_STAYS:
                self.state = PowerState.OPERATION_ENABLED  # 16
            return self.state
        self.state = _TRANSITIONS.get((s, cmd), s)
        return self.state

    def on_sync(self) -> None:
        """Automatic transitions at a SYNC: a finished quick stop (codes 0..4) ends SWITCH ON DISABLED."""
        if self.state is PowerState.QUICK_STOP_ACTIVE and self.quick_stop_option not in QUICK_STOP_STAYS:
            self.state = PowerState.SWITCH_ON_DISABLED  # 12

    def fault(self) -> bool:
        """A fault: FAULT REACTION ACTIVE then (torque zeroed by the caller) FAULT. False if already."""
        if self.state in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE):
            return False
        self.state = PowerState.FAULT_REACTION_ACTIVE  # 13
        return True

    def fault_reaction_done(self) -> None:
        if self.state is PowerState.FAULT_REACTION_ACTIVE:
            self.state = PowerState.FAULT  # 14
