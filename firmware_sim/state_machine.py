"""The drive state machine: DISABLED, ENABLED, FAULT (the protocol's :class:`DriveState`).

Transitions on CONTROL requests, from a table; every other (state, request) pair leaves the
state as it is. Any fault moves to FAULT from every state; only CLEAR_FAULT leaves FAULT, and it
leads to DISABLED (the host must enable again).
"""

from __future__ import annotations

from typing import Final

from dob_hil.link.protocol import ControlRequest, DriveState, FaultCode

TRANSITIONS: Final[dict[tuple[DriveState, ControlRequest], DriveState]] = {
    (DriveState.DISABLED, ControlRequest.ENABLE): DriveState.ENABLED,
    (DriveState.ENABLED, ControlRequest.DISABLE): DriveState.DISABLED,
    (DriveState.FAULT, ControlRequest.CLEAR_FAULT): DriveState.DISABLED,
}


class DriveStateMachine:
    def __init__(self) -> None:
        self.state = DriveState.DISABLED
        self.fault_code: FaultCode | None = None  # the fault that put the drive in FAULT

    def request(self, request: ControlRequest) -> DriveState:
        """Apply a CONTROL request; returns the new state (unchanged if the request does not apply)."""
        new = TRANSITIONS.get((self.state, request), self.state)
        if self.state is DriveState.FAULT and new is not DriveState.FAULT:
            self.fault_code = None
        self.state = new
        return new

    def fault(self, code: FaultCode) -> bool:
        """Enter FAULT; False (and the first fault code kept) if already in FAULT."""
        if self.state is DriveState.FAULT:
            return False
        self.state = DriveState.FAULT
        self.fault_code = code
        return True
