"""PDO configuration of the simulated drive: SDO write checks (CiA 301) and the active layouts.

The mapping is configured over SDO with the standard sequence: set bit 31 of the COB-ID (PDO not
valid), set the number of mapped objects to 0, write the entries, set the number, clear bit 31.
:func:`check_pdo_write` refuses what CiA 301 forbids, with its abort code:

* a COB-ID change while the PDO is valid, or an extended (29-bit) COB-ID: 0x06090030;
* a transmission type the drive does not serve (TPDO: 0..240, synchronous; RPDO: 0..240 applied
  at the next SYNC, 254/255 applied on reception): 0x06090030;
* a mapping write while the PDO is valid, or an entry write while the count is not 0: 0x06010000;
* a count above 8: 0x06090031; an entry naming a missing object: 0x06020000; an object that cannot
  be mapped (PDOMapping not set, wrong direction of access, wrong length): 0x06040041; more than
  64 bits: 0x06040042.

After a write the layouts are rebuilt (lazily, :meth:`PdoLayouts.refresh`) with ``canopen``'s own
:class:`canopen.pdo.PdoMap` reading the node's object dictionary; each map becomes a ``struct``
layout so the cyclic path packs and unpacks without per-variable objects.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import canopen
from canopen import SdoAbortedError, objectdictionary
from canopen.pdo import PdoMap

from firmware_sim.cia402.objects import (
    ABORT_INVALID_VALUE,
    ABORT_NOT_IN_OD,
    ABORT_NOT_MAPPABLE,
    ABORT_PDO_LENGTH,
    ABORT_UNSUPPORTED_ACCESS,
    ABORT_VALUE_TOO_HIGH,
    N_PDO,
    PDO_EXTENDED,
    PDO_INVALID,
    RPDO_COMM,
    RPDO_MAP,
    TPDO_COMM,
    TPDO_MAP,
)

MAX_ENTRIES = 8
MAX_BITS = 64
_FORMATS = {
    objectdictionary.INTEGER8: "b",
    objectdictionary.UNSIGNED8: "B",
    objectdictionary.INTEGER16: "h",
    objectdictionary.UNSIGNED16: "H",
    objectdictionary.INTEGER32: "i",
    objectdictionary.UNSIGNED32: "I",
}


def _u32(node: canopen.LocalNode, index: int, subindex: int) -> int:
    return int.from_bytes(node.get_data(index, subindex), "little")


def _mapped_object(node: canopen.LocalNode, entry: int, receive: bool) -> int:
    """The length in bits of a mapping entry's object, or an SdoAbortedError."""
    index, subindex, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
    od = node.object_dictionary
    if index not in od:
        raise SdoAbortedError(ABORT_NOT_IN_OD)
    obj = od[index]
    if not isinstance(obj, objectdictionary.ODVariable):
        if subindex not in obj:
            raise SdoAbortedError(ABORT_NOT_IN_OD)
        obj = obj[subindex]
    accessible = obj.writable if receive else obj.readable
    if not obj.pdo_mappable or not accessible or obj.data_type not in _FORMATS or bits != len(obj):
        raise SdoAbortedError(ABORT_NOT_MAPPABLE)
    return bits


def check_pdo_write(node: canopen.LocalNode, index: int, subindex: int, value: int) -> bool:
    """Check an SDO write to a PDO parameter; True if it is one (the layouts must be refreshed)."""
    for comm, mapping, receive in ((RPDO_COMM, RPDO_MAP, True), (TPDO_COMM, TPDO_MAP, False)):
        if comm <= index < comm + N_PDO:
            _check_comm(node, index, subindex, value, receive)
            return True
        if mapping <= index < mapping + N_PDO:
            _check_mapping(node, comm + index - mapping, index, subindex, value, receive)
            return True
    return False


def _check_comm(node: canopen.LocalNode, index: int, subindex: int, value: int, receive: bool) -> None:
    if subindex == 1:
        current = _u32(node, index, 1)
        if value & PDO_EXTENDED:
            raise SdoAbortedError(ABORT_INVALID_VALUE)
        both_valid = not (value & PDO_INVALID) and not (current & PDO_INVALID)
        if both_valid and (value & 0x7FF) != (current & 0x7FF):
            raise SdoAbortedError(ABORT_INVALID_VALUE)
    elif subindex == 2 and not (value <= 240 or (receive and value >= 254)):
        raise SdoAbortedError(ABORT_INVALID_VALUE)


def _check_mapping(
    node: canopen.LocalNode, comm: int, index: int, subindex: int, value: int, receive: bool
) -> None:
    if not _u32(node, comm, 1) & PDO_INVALID:
        raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)  # the PDO must be made invalid first
    if subindex == 0:
        if value > MAX_ENTRIES:
            raise SdoAbortedError(ABORT_VALUE_TOO_HIGH)
        bits = sum(_mapped_object(node, _u32(node, index, i), receive) for i in range(1, value + 1))
        if bits > MAX_BITS:
            raise SdoAbortedError(ABORT_PDO_LENGTH)
        return
    if node.get_data(index, 0)[0] != 0:
        raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)  # the count must be set to 0 first
    if value:
        _mapped_object(node, value, receive)


@dataclass(frozen=True)
class Layout:
    """One valid PDO: its COB-ID, transmission type, mapped objects and their packing."""

    cob_id: int
    trans_type: int
    objects: tuple[tuple[int, int], ...]  # (index, subindex) in frame order
    packer: struct.Struct
    sync_start: int = 0

    @property
    def size(self) -> int:
        return self.packer.size


def _layout(pdo_map: PdoMap) -> Layout | None:
    pdo_map.read()  # canopen reads the COB-ID, type and entries from the node (our own OD)
    if not pdo_map.enabled or pdo_map.cob_id is None:
        return None
    fmt = "<" + "".join(_FORMATS[var.od.data_type or 0] for var in pdo_map.map)
    return Layout(
        cob_id=pdo_map.cob_id & 0x7FF,
        trans_type=int(pdo_map.trans_type or 0),
        objects=tuple((var.index, var.subindex) for var in pdo_map.map),
        packer=struct.Struct(fmt),
        sync_start=int(pdo_map.sync_start_value or 0),
    )


class PdoLayouts:
    """The node's valid RPDOs (by COB-ID) and TPDOs (in order), rebuilt after a PDO parameter write."""

    def __init__(self, node: canopen.LocalNode) -> None:
        self.node = node
        self.rpdos: dict[int, Layout] = {}
        self.tpdos: tuple[Layout, ...] = ()
        self.stale = True

    def refresh(self) -> None:
        if not self.stale:
            return
        self.stale = False
        assert self.node.rpdo.map is not None and self.node.tpdo.map is not None
        rpdos = [_layout(m) for m in self.node.rpdo.map.values()]
        self.rpdos = {lay.cob_id: lay for lay in rpdos if lay is not None}
        tpdos = [_layout(m) for m in self.node.tpdo.map.values()]
        self.tpdos = tuple(lay for lay in tpdos if lay is not None)
