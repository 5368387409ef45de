"""A minimal CiA 402 slave built on ``canopen.LocalNode`` (not firmware_sim): the host link's peer in
tests that must not depend on our own simulated drive.

canopen's LocalNode serves the SDOs from the shipped EDS; this adds the least of CiA 402 the host
needs: the power state machine driven by 0x6040 (SDO or RPDO1), 0x6041 and 0x6061 answered from it,
and TPDO1 (statusword, position) sent on every SYNC while NMT operational. It runs on its own
notifier thread (real time).
"""

from __future__ import annotations

import struct
import threading
from typing import Any

import can
import canopen

from dob_hil.link.cia402 import codec
from dob_hil.link.cia402.options import DEFAULT_EDS

SOD, RTSO, SO, OE, QSA, FAULT = 0x0040, 0x0021, 0x0023, 0x0027, 0x0007, 0x0008


class PeerDrive:
    def __init__(
        self,
        bus: can.BusABC,
        node_id: int = 1,
        *,
        statusword: int = SOD,
        stuck: bool = False,
        values: dict[tuple[int, int], int] | None = None,
        error_code: int = 0,
    ) -> None:
        self.node_id = node_id
        self.statusword = statusword
        self.stuck = stuck  # ignore every controlword
        self.position = 0
        self.rpdos: list[tuple[int, int]] = []
        self.syncs = 0
        self.controlwords: list[int] = []
        self.mode = 0
        self.nmt_commands: list[int] = []
        self._cw_last = 0
        self._lock = threading.Lock()
        self.network = canopen.Network(bus)
        self.node = canopen.LocalNode(node_id, str(DEFAULT_EDS))
        self.network.add_node(self.node)
        self.node.add_read_callback(self._read)
        self.node.add_write_callback(self._write)
        defaults = {(0x6075, 0): 500, (0x6076, 0): 100, (0x6072, 0): 2000, (0x608F, 1): 10000,
                    (0x608F, 2): 1, (0x603F, 0): error_code}  # fmt: skip
        defaults.update(values or {})
        for (index, sub), value in defaults.items():
            od = self._od(index, sub)
            self.node.data_store.setdefault(index, {})[sub] = od.encode_raw(value)
        self.network.subscribe(codec.SYNC_ID, self._on_sync)
        self.network.subscribe(codec.RPDO1_BASE + node_id, self._on_rpdo)
        self.network.subscribe(codec.NMT_ID, self._on_nmt)
        self.network.notifier = can.Notifier(bus, self.network.listeners, 0.05)

    def stop(self) -> None:
        assert self.network.notifier is not None
        self.network.notifier.stop()

    def stored(self, index: int, sub: int = 0) -> int:
        od = self._od(index, sub)
        return int(od.decode_raw(self.node.data_store[index][sub]))

    def _od(self, index: int, sub: int) -> Any:
        entry = self.node.object_dictionary[index]
        return entry[sub] if hasattr(entry, "subindices") else entry

    # --- canopen callbacks ----------------------------------------------------------------------------
    def _read(self, index: int, subindex: int, od: Any) -> int | None:
        if index == 0x6041:
            return self.statusword
        if index == 0x6061:
            return self.mode
        return None

    def _write(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        if index == 0x6040:
            self._controlword(int(od.decode_raw(data)))
        elif index == 0x6060:
            self.mode = int(od.decode_raw(data))

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) == 2 and data[1] in (0, self.node_id):
            self.nmt_commands.append(data[0])

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._lock:
            self.syncs += 1
            if self.nmt_commands and self.nmt_commands[-1] == codec.NmtCommand.START:
                payload = struct.pack("<Hi", self.statusword, self.position)
                self.network.send_message(codec.TPDO1_BASE + self.node_id, payload)

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        cw, torque = struct.unpack("<Hh", bytes(data))
        with self._lock:
            self.rpdos.append((cw, torque))
        self._controlword(cw)

    def _controlword(self, cw: int) -> None:
        self.controlwords.append(cw)
        rising_reset = cw & 0x80 and not self._cw_last & 0x80
        self._cw_last = cw
        if self.stuck:
            return
        sw = self.statusword & 0x6F
        if self.statusword & 0x4F == FAULT:
            if rising_reset:
                self.statusword = SOD
            return
        if cw & 0x82 == 0:  # disable voltage
            self.statusword = SOD
        elif cw & 0x87 == 0x02:  # quick stop
            self.statusword = QSA if sw == OE else SOD
        elif cw & 0x87 == 0x06:  # shutdown
            if self.statusword & 0x4F == SOD or sw in (SO, OE, RTSO):
                self.statusword = RTSO
        elif cw & 0x8F == 0x07:  # switch on / disable operation
            if sw in (RTSO, OE, SO):
                self.statusword = SO
        elif cw & 0x8F == 0x0F and sw in (SO, OE, QSA):  # enable operation
            self.statusword = OE
