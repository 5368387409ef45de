"""Choices a correct drive may make where PROTOCOL.md leaves it free, and deliberate deviations.

:class:`DriveBehaviour` is passed to :class:`~firmware_sim.drive.SimulatedDrive` (default: the
reference behaviour). The first three options are *permitted* variants: a host built from the spec
must work with each (the tests and the conformance kit's self-test run them). The last two are
*violations*, for showing that the conformance kit catches a non-conforming drive.
"""

from __future__ import annotations

from dataclasses import dataclass

from dob_hil.link.protocol import PROTOCOL_VERSION


@dataclass(frozen=True)
class DriveBehaviour:
    # permitted by PROTOCOL.md
    restart_sequence_on_enable: bool = False  # FEEDBACK sequence starts at 0 on entering ENABLED
    fault_on_command_while_disabled: bool = False  # a COMMAND while DISABLED: FAULT code 5
    pad_frames: bool = False  # every frame sent padded with zeros to 8 bytes
    # violations (for the conformance kit's self-test)
    protocol_version: int = PROTOCOL_VERSION  # the version the drive speaks and accepts
    stale_stop_ignored: bool = False  # a stale COMMAND with Enable=0 does not stop (protocol 1)

    @property
    def conforming(self) -> bool:
        return self.protocol_version == PROTOCOL_VERSION and not self.stale_stop_ignored


REFERENCE = DriveBehaviour()

VARIANTS: dict[str, DriveBehaviour] = {
    "reference": REFERENCE,
    "restart-sequence": DriveBehaviour(restart_sequence_on_enable=True),
    "fault-on-command-while-disabled": DriveBehaviour(fault_on_command_while_disabled=True),
    "padded": DriveBehaviour(pad_frames=True),
    "version-1": DriveBehaviour(protocol_version=1),
    "stale-stop-ignored": DriveBehaviour(stale_stop_ignored=True),
}
