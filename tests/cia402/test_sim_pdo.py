"""PDO mapping over SDO (canopen's PDO API and raw abort codes) and the PDO frames byte for byte."""

from __future__ import annotations

import struct

import canopen
import pytest
from sim_support import NODE, make_config, master_rig, raw_rig, sdo_request

from firmware_sim.cia402.objects import shipped_eds

TPDO1, TPDO2, RPDO1 = 0x180 + NODE, 0x280 + NODE, 0x200 + NODE
EMCY = 0x80 + NODE


def _remap_with_canopen(node: canopen.BaseNode402) -> None:
    """The standard sequence, done by canopen's own PdoMap.save()."""
    node.tpdo.read()
    node.rpdo.read()
    tpdo = node.tpdo[1]
    tpdo.clear()
    tpdo.add_variable(0x6041)
    tpdo.add_variable(0x6064)
    tpdo.add_variable(0x6077)
    tpdo.trans_type = 1
    tpdo.enabled = True
    node.tpdo[2].enabled = False
    rpdo = node.rpdo[1]
    rpdo.clear()
    rpdo.add_variable(0x6040)
    rpdo.add_variable(0x6071)
    rpdo.trans_type = 1
    rpdo.enabled = True
    node.tpdo.save()
    node.rpdo.save()


def test_remapping_through_canopen_and_frames_decoded_by_its_maps() -> None:
    with master_rig() as rig:
        node = rig.node
        _remap_with_canopen(node)
        # a second, independent reader of the drive's configuration sees the same maps
        other = canopen.RemoteNode(NODE, str(shipped_eds()))
        other.sdo = node.sdo  # same SDO client, fresh PDO objects
        other.tpdo = canopen.pdo.TPDO(other)
        other.tpdo.network = rig.network
        other.tpdo.read()
        assert [(v.index, v.length) for v in other.tpdo[1]] == [(0x6041, 16), (0x6064, 32), (0x6077, 16)]
        assert not other.tpdo[2].enabled

        node.sdo[0x6060].raw = 10
        node.nmt.state = "OPERATIONAL"
        for cw in (0x06, 0x07, 0x0F):
            node.sdo[0x6040].raw = cw
        node.rpdo[1]["Controlword"].raw = 0x0F
        node.rpdo[1]["Target torque"].raw = 120
        received: list[dict[int, int]] = []  # decoded by canopen's map (no wait_for_reception race)
        node.tpdo[1].add_callback(lambda m: received.append({v.index: v.raw for v in m}))
        for k in range(3):
            node.rpdo[1].transmit()
            node.network.sync.transmit()
            rig.wait_for(lambda k=k: len(received) > k, "the TPDO of the SYNC")
            values = received[k]
            assert values[0x6041] == 0x1237  # operation enabled, remote, follows the command
            assert values[0x6077] == (0 if k == 0 else 120)  # the setpoint acts from the SYNC after it
        rig.wait_for(lambda: sum(m.arbitration_id == TPDO1 for m in rig.frames) >= 3, "three TPDO1")
        tpdo_frames = [bytes(m.data) for m in rig.frames if m.arbitration_id == TPDO1]
        last = tpdo_frames[-1]
        assert last == struct.pack("<HiH", 0x1237, rig.drive.core.counts, 120)
        assert not any(m.arbitration_id == TPDO2 for m in rig.frames)  # disabled by the remap


@pytest.mark.parametrize(
    ("writes", "code"),
    [
        ([(0x2F, 0x1A00, 0, b"\x00")], 0x06010000),  # mapping of a valid PDO
        ([(0x23, 0x1800, 1, (0x190 + NODE).to_bytes(4, "little"))], 0x06090030),  # COB-ID while valid
        ([(0x23, 0x1800, 1, (0x2000_0000 | 0x180 + NODE).to_bytes(4, "little"))], 0x06090030),
        ([(0x2F, 0x1800, 2, b"\xff")], 0x06090030),  # event-driven TPDOs are not served
        (
            [
                (0x23, 0x1800, 1, (0x8000_0000 | 0x180 + NODE).to_bytes(4, "little")),
                (0x23, 0x1A00, 1, (0x60410010).to_bytes(4, "little")),
            ],
            0x06010000,
        ),  # count not 0 first
        (
            [
                (0x23, 0x1800, 1, (0x8000_0000 | 0x180 + NODE).to_bytes(4, "little")),
                (0x2F, 0x1A00, 0, b"\x00"),
                (0x23, 0x1A00, 1, (0x10000020).to_bytes(4, "little")),
            ],
            0x06040041,
        ),  # 0x1000 not mappable
        (
            [
                (0x23, 0x1800, 1, (0x8000_0000 | 0x180 + NODE).to_bytes(4, "little")),
                (0x2F, 0x1A00, 0, b"\x00"),
                (0x23, 0x1A00, 1, (0x60410020).to_bytes(4, "little")),
            ],
            0x06040041,
        ),  # wrong length
        (
            [
                (0x23, 0x1800, 1, (0x8000_0000 | 0x180 + NODE).to_bytes(4, "little")),
                (0x2F, 0x1A00, 0, b"\x00"),
                (0x23, 0x1A00, 1, (0x21000010).to_bytes(4, "little")),
            ],
            0x06020000,
        ),  # no such object
        (
            [
                (0x23, 0x1400, 1, (0x8000_0000 | 0x200 + NODE).to_bytes(4, "little")),
                (0x2F, 0x1600, 0, b"\x00"),
                (0x23, 0x1600, 1, (0x60410010).to_bytes(4, "little")),
            ],
            0x06040041,
        ),  # read-only in an RPDO
        (
            [
                (0x23, 0x1800, 1, (0x8000_0000 | 0x180 + NODE).to_bytes(4, "little")),
                (0x2F, 0x1A00, 0, b"\x00"),
                (0x23, 0x1A00, 1, (0x60640020).to_bytes(4, "little")),
                (0x23, 0x1A00, 2, (0x606C0020).to_bytes(4, "little")),
                (0x23, 0x1A00, 3, (0x60410010).to_bytes(4, "little")),
                (0x2F, 0x1A00, 0, b"\x03"),
            ],
            0x06040042,
        ),  # 80 bits
        (
            [
                (0x23, 0x1800, 1, (0x8000_0000 | 0x180 + NODE).to_bytes(4, "little")),
                (0x2F, 0x1A00, 0, b"\x09"),
            ],
            0x06090031,
        ),  # more than 8 entries
    ],
    ids=lambda v: f"{v:08X}" if isinstance(v, int) else f"{len(v)}-writes",
)
def test_mapping_rules_abort_with_cia301_codes(writes: list[tuple[int, int, int, bytes]], code: int) -> None:
    with raw_rig() as rig:
        *setup, last = writes
        for cs, index, subindex, payload in setup:
            assert rig.sdo(sdo_request(cs, index, subindex, payload))[0] == 0x60
        cs, index, subindex, payload = last
        assert rig.sdo(sdo_request(cs, index, subindex, payload)) == (
            bytes([0x80]) + index.to_bytes(2, "little") + bytes([subindex]) + code.to_bytes(4, "little")
        )


def _map_tpdo1(rig, trans_type: int, entries: list[int]) -> None:  # type: ignore[no-untyped-def]
    cob = 0x180 + NODE
    rig.write(0x1800, 1, 0x8000_0000 | cob, 4)
    rig.write(0x1A00, 0, 0, 1)
    for i, entry in enumerate(entries, 1):
        assert rig.write(0x1A00, i, entry, 4)[0] == 0x60
    assert rig.write(0x1A00, 0, len(entries), 1)[0] == 0x60
    assert rig.write(0x1800, 2, trans_type, 1)[0] == 0x60
    assert rig.write(0x1800, 1, cob, 4)[0] == 0x60


def test_tpdo_transmission_types_every_nth_sync_and_on_change() -> None:
    with raw_rig() as rig:
        _map_tpdo1(rig, 3, [0x60410010])
        rig.write(0x1801, 1, 0x8000_0000 | TPDO2, 4)
        rig.exchange(0x000, bytes([0x01, NODE]))
        sent = [any(m.arbitration_id == TPDO1 for m in rig.sync()) for _ in range(9)]
        assert sent == [False, False, True] * 3
        rig.exchange(0x000, bytes([0x80, NODE]))
        _map_tpdo1(rig, 0, [0x60410010])  # acyclic synchronous: at a SYNC, when the data changed
        rig.exchange(0x000, bytes([0x01, NODE]))
        first = [bytes(m.data) for m in rig.sync() if m.arbitration_id == TPDO1]
        again = [m for m in rig.sync() if m.arbitration_id == TPDO1]
        rig.write(0x6040, 0, 0x06, 2)  # statusword changes: READY TO SWITCH ON
        changed = [bytes(m.data) for m in rig.sync() if m.arbitration_id == TPDO1]
        assert first == [b"\x40\x02"] and again == [] and changed == [b"\x21\x02"]


def test_pdos_only_in_operational() -> None:
    with raw_rig() as rig:
        assert [m for m in rig.sync() if m.arbitration_id in (TPDO1, TPDO2)] == []  # PRE-OPERATIONAL
        rig.exchange(RPDO1, b"\x06\x00\x00\x00")
        rig.sync()
        assert rig.drive.state.value == "SWITCH ON DISABLED"
        rig.exchange(0x000, bytes([0x01, NODE]))
        assert {m.arbitration_id for m in rig.sync()} == {TPDO1, TPDO2}


def test_rpdo_synchronous_waits_for_sync_asynchronous_acts_at_once() -> None:
    with raw_rig() as rig:
        rig.exchange(0x000, bytes([0x01, NODE]))
        rig.exchange(RPDO1, b"\x06\x00\x00\x00")  # type 1: latched
        assert rig.drive.state.value == "SWITCH ON DISABLED"
        rig.sync()
        assert rig.drive.state.value == "READY TO SWITCH ON"
        rig.write(0x1400, 2, 255, 1)
        rig.exchange(RPDO1, b"\x07\x00\x00\x00")  # type 255: on reception
        assert rig.drive.state.value == "SWITCHED ON"


def test_rpdo_length_errors_send_emcy() -> None:
    with raw_rig() as rig:
        rig.exchange(0x000, bytes([0x01, NODE]))
        short = rig.exchange(RPDO1, b"\x06\x00\x00")
        assert [(m.arbitration_id, bytes(m.data).hex()) for m in short] == [(EMCY, "1082000000000000")]
        rig.sync()
        assert rig.drive.state.value == "SWITCH ON DISABLED"  # not processed
        long = rig.exchange(RPDO1, b"\x06\x00\x00\x00\x00")
        assert [(m.arbitration_id, bytes(m.data).hex()) for m in long] == [(EMCY, "2082000000000000")]
        rig.sync()
        assert rig.drive.state.value == "READY TO SWITCH ON"  # processed


def test_sync_counter_length_checked_against_0x1019() -> None:
    with raw_rig() as rig:
        rig.exchange(0x000, bytes([0x01, NODE]))
        frames = rig.exchange(0x80, b"\x01")  # a counter while 0x1019 = 0: EMCY 0x8240 once, still a SYNC
        assert [bytes(m.data).hex() for m in frames if m.arbitration_id == EMCY] == ["4082000000000000"]
        assert any(m.arbitration_id == TPDO1 for m in frames)
        assert not any(m.arbitration_id == EMCY for m in rig.exchange(0x80, b"\x02"))
        assert rig.write(0x1019, 0, 240, 1)[0] == 0x60
        assert not any(m.arbitration_id == EMCY for m in rig.exchange(0x80, b"\x03"))
        frames = rig.exchange(0x80, b"\x04\x00")  # DLC 2 is no SYNC at all
        assert [bytes(m.data).hex() for m in frames if m.arbitration_id == EMCY] == ["4082000000000000"]
        assert rig.drive.stats.syncs == 3


def test_tpdo_loss_is_seeded_and_lockstep_is_deterministic() -> None:
    def run() -> tuple[list[int], list[tuple[float, ...]]]:
        with raw_rig(make_config(sim={"loss_probability": 0.3, "seed": 5})) as rig:
            rig.enable()
            got = []
            for k in range(60):
                got.append(sum(m.arbitration_id == TPDO1 for m in rig.sync()))
                rig.exchange(RPDO1, b"\x0f\x00" + (k * 7 % 300).to_bytes(2, "little"))
            return got, [t.state for t in rig.truths]

    first, second = run(), run()
    assert first == second
    assert 0 < sum(first[0]) < 60  # some lost, not all
