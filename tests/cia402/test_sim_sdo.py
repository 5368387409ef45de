"""The simulated drive's SDO server, byte for byte against CiA 301 and through canopen's SDO client."""

from __future__ import annotations

import canopen
import pytest
from sim_support import NODE, master_rig, raw_rig, sdo_request

from firmware_sim.cia402.objects import shipped_eds


def test_expedited_uploads_byte_for_byte() -> None:
    with raw_rig() as rig:
        # 4 bytes: 0x43 (expedited, size indicated, n = 0), device type 0x00020192
        assert rig.sdo(sdo_request(0x40, 0x1000, 0)) == bytes.fromhex("43 00 10 00 92 01 02 00")
        # 2 bytes: 0x4B (n = 2), statusword SWITCH ON DISABLED + remote = 0x0240
        assert rig.sdo(sdo_request(0x40, 0x6041, 0)) == bytes.fromhex("4B 41 60 00 40 02 00 00")
        # 1 byte: 0x4F (n = 3), error register 0
        assert rig.sdo(sdo_request(0x40, 0x1001, 0)) == bytes.fromhex("4F 01 10 00 00 00 00 00")
        # a record's sub-index: identity vendor id (the EDS's example value)
        assert rig.sdo(sdo_request(0x40, 0x1018, 1)) == bytes.fromhex("43 18 10 01 B1 D0 00 00")


def test_expedited_download_is_confirmed_and_read_back() -> None:
    with raw_rig() as rig:
        assert rig.sdo(sdo_request(0x2B, 0x6072, 0, (1500).to_bytes(2, "little"))) == bytes.fromhex(
            "60 72 60 00 00 00 00 00"
        )
        assert rig.sdo(sdo_request(0x40, 0x6072, 0)) == bytes.fromhex("4B 72 60 00 DC 05 00 00")


@pytest.mark.parametrize(
    ("request_bytes", "code"),
    [
        (sdo_request(0x40, 0x2000, 0), 0x06020000),  # object does not exist
        (sdo_request(0x40, 0x1018, 7), 0x06090011),  # sub-index does not exist
        (sdo_request(0x2B, 0x6041, 0, b"\x06\x00"), 0x06010002),  # write a read-only object
        (sdo_request(0x23, 0x6040, 0, b"\x06\x00\x00\x00"), 0x06070010),  # length does not match
        (sdo_request(0x2F, 0x6060, 0, b"\x03"), 0x06090030),  # a mode the drive does not have
        (sdo_request(0x2B, 0x605A, 0, b"\x09\x00"), 0x06090030),  # quick stop option code out of range
        (sdo_request(0x23, 0x608F, 1, (4096).to_bytes(4, "little")), 0x06090030),  # not our encoder
        (sdo_request(0x23, 0x1003, 0, b"\x01"), 0x06070010),  # u8 written with 4 bytes
        (sdo_request(0x2F, 0x1003, 0, b"\x01"), 0x06090030),  # only 0 clears the error history
        (sdo_request(0xE0, 0x1000, 0), 0x05040001),  # no such command specifier
    ],
    ids=lambda v: f"{v:08X}" if isinstance(v, int) else v[:4].hex(),
)
def test_abort_frames_byte_for_byte(request_bytes: bytes, code: int) -> None:
    with raw_rig() as rig:
        reply = rig.sdo(request_bytes)
        expected = bytes([0x80]) + request_bytes[1:4] + code.to_bytes(4, "little")
        assert reply == expected


def test_segmented_upload_of_a_visible_string() -> None:
    with raw_rig() as rig:
        name = b"dob_hil generic CiA 402 servo drive (example)"
        init = rig.sdo(sdo_request(0x40, 0x1008, 0))
        assert init == bytes([0x41, 0x08, 0x10, 0x00]) + len(name).to_bytes(4, "little")
        received, toggle = b"", 0
        while True:
            seg = rig.sdo(bytes([0x60 | toggle << 4]) + bytes(7))
            assert seg[0] & 0xE0 == 0x00 and (seg[0] >> 4) & 1 == toggle
            unused = (seg[0] >> 1) & 0x7
            received += seg[1 : 8 - unused]
            toggle ^= 1
            if seg[0] & 0x01:
                break
        assert received == name
        # a toggle bit that does not alternate aborts with 0x05030000
        rig.sdo(sdo_request(0x40, 0x1008, 0))
        assert rig.sdo(bytes([0x70]) + bytes(7))[4:] == (0x05030000).to_bytes(4, "little")


def test_canopen_client_reads_and_writes_expedited_and_segmented() -> None:
    with master_rig() as rig:
        sdo = rig.node.sdo
        assert sdo[0x1008].raw == "dob_hil generic CiA 402 servo drive (example)"  # segmented upload
        assert sdo[0x1000].raw == 0x00020192
        assert sdo[0x1018][1].raw == 0x0000D0B1
        assert sdo[0x6075].raw == 500  # rated current from drive.dac_lsb_A = 0.5 mA
        assert (sdo[0x608F][1].raw, sdo[0x608F][2].raw) == (10000, 1)
        sdo.download(0x1006, 0, (300).to_bytes(4, "little"), force_segment=True)  # segmented download
        assert sdo[0x1006].raw == 300
        assert rig.drive.core.period_ns == 300_000
        sdo[0x6072].raw = 1200
        assert sdo[0x6072].raw == 1200
        with pytest.raises(canopen.SdoAbortedError) as missing:
            sdo.upload(0x2000, 0)
        assert missing.value.code == 0x06020000
        with pytest.raises(canopen.SdoAbortedError) as read_only:
            sdo[0x6064].raw = 5
        assert read_only.value.code == 0x06010002


def test_sdo_is_silent_in_stopped_and_answers_again_after_start() -> None:
    with raw_rig() as rig:
        rig.exchange(0x000, bytes([0x02, NODE]))  # NMT stop
        assert rig.exchange(0x600 + NODE, sdo_request(0x40, 0x1000, 0)) == []
        rig.exchange(0x000, bytes([0x80, NODE]))  # pre-operational
        assert rig.sdo(sdo_request(0x40, 0x1000, 0))[0] == 0x43


def test_short_sdo_frames_and_other_nodes_are_ignored() -> None:
    with raw_rig() as rig:
        assert rig.exchange(0x600 + NODE, b"\x40\x00\x10") == []
        assert rig.exchange(0x600 + NODE + 1, sdo_request(0x40, 0x1000, 0)) == []
        assert rig.drive.stats.frames_ignored == 2


def test_shipped_eds_is_a_cia402_servo_for_canopen() -> None:
    od = canopen.import_od(str(shipped_eds()), NODE)
    assert od[0x1000].default == 0x00020192
    assert od[0x6502].default & (1 << 9)  # cyclic synchronous torque supported
    assert od[0x6072].default == 2000 and od[0x608F][1].default == 10000
    assert od[0x1400][1].default == 0x200 + NODE and od[0x1800][1].default == 0x180 + NODE
    assert od[0x1014].default == 0x80 + NODE
    for index in (0x6040, 0x6071, 0x6041, 0x6064, 0x606C, 0x603F, 0x6077):
        assert od[index].pdo_mappable, hex(index)


def test_a_segment_request_without_a_transfer_is_aborted_not_fatal() -> None:
    with raw_rig() as rig:
        reply = rig.sdo(bytes([0x60]) + bytes(7))  # upload segment, nothing initiated
        assert reply[0] == 0x80 and reply[4:] == (0x05040001).to_bytes(4, "little")
        assert rig.sdo(sdo_request(0x40, 0x1000, 0))[0] == 0x43  # still serving
