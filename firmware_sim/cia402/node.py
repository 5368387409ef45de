"""The drive's CANopen node: ``canopen``'s LocalNode (SDO server, OD, NMT slave) on a clock we own.

``canopen`` produces heartbeats with python-can periodic tasks (wall clock); the simulated drive
needs them on its own clock (simulated time in lockstep), so :class:`DriveNmt` keeps the producer
time and leaves the sending to the drive (:meth:`Cia402Core.tick`). NMT reset node / reset
communication are handed to the drive (it restores its object dictionary, sends the boot-up and
enters PRE-OPERATIONAL), which ``canopen``'s slave does not do on its own.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import can
import canopen
from canopen.nmt import NmtSlave

NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82
NMT_ENTER_PRE_OPERATIONAL = 0x80
NMT_STATE_CODES = {"INITIALISING": 0x00, "STOPPED": 0x04, "OPERATIONAL": 0x05, "PRE-OPERATIONAL": 0x7F}


class DriveNmt(NmtSlave):
    """NMT slave whose heartbeat the drive sends on its own clock."""

    def __init__(self, node_id: int, local_node: canopen.LocalNode) -> None:
        super().__init__(node_id, local_node)
        self.heartbeat_ms = 0
        self.heartbeat_changed = False  # the drive restarts its heartbeat schedule
        self.on_reset: Callable[[int], None] | None = None

    def start_heartbeat(self, heartbeat_time_ms: int) -> None:
        self.heartbeat_ms = heartbeat_time_ms
        self.heartbeat_changed = True

    def stop_heartbeat(self) -> None:
        self.heartbeat_ms = 0
        self.heartbeat_changed = True

    def update_heartbeat(self) -> None:
        pass  # the drive reads the state when it sends

    def on_command(self, can_id: int, data: Any, timestamp: float) -> None:
        cmd, target = data[0], data[1]
        if target not in (0, self.id):
            return
        if cmd in (NMT_RESET_NODE, NMT_RESET_COMMUNICATION) and self.on_reset is not None:
            self.on_reset(cmd)
            return
        super().on_command(can_id, data, timestamp)  # type: ignore[no-untyped-call]

    def boot(self) -> None:
        """INITIALISING: the boot-up message, then PRE-OPERATIONAL (heartbeat from 0x1017)."""
        self.send_command(NMT_RESET_NODE)  # state 0: canopen sends the boot-up frame
        self.send_command(NMT_ENTER_PRE_OPERATIONAL)

    @property
    def state_code(self) -> int:
        return NMT_STATE_CODES.get(self.state, 0)


class DriveNode(canopen.LocalNode):
    """A LocalNode with :class:`DriveNmt` in place of canopen's periodic-task heartbeat."""

    def __init__(self, node_id: int, object_dictionary: canopen.ObjectDictionary) -> None:
        super().__init__(node_id, object_dictionary)
        self._write_callbacks.remove(self.nmt.on_write)  # the stock NMT slave's heartbeat task
        self.nmt: DriveNmt = DriveNmt(node_id, self)
        self.on_write(self.nmt.on_write)

    def on_read(self, callback: Callable[..., Any]) -> None:
        """``callback(index=, subindex=, od=)`` returns an object's value, or None for the stored one."""
        self._read_callbacks.append(callback)

    def on_write(self, callback: Callable[..., Any]) -> None:
        """``callback(index=, subindex=, od=, data=)`` runs before a write is stored; it may abort it."""
        self._write_callbacks.append(callback)


class DriveNetwork(canopen.Network):
    """A canopen Network without a Notifier (the drive feeds it) that can be muted."""

    def __init__(self, bus: can.BusABC) -> None:
        super().__init__(bus)
        self.muted = False  # an injected "silent" fault: nothing leaves the drive
        self.suppressed = 0
        self.send_failures = 0

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        if self.muted:
            self.suppressed += 1
            return
        try:
            super().send_message(can_id, data, remote)
        except can.CanError:
            self.send_failures += 1
