"""The host's CiA 301/402 codec byte for byte, and against the ``canopen`` library's own tables,
PDO maps and EMCY consumer (an implementation that is not ours)."""

from __future__ import annotations

import functools
import struct

import canopen
import pytest
from canopen.emcy import EmcyConsumer
from canopen.nmt import NMT_COMMANDS
from canopen.profiles.p402 import State402
from hypothesis import given, settings
from hypothesis import strategies as st

from dob_hil.errors import ProtocolError
from dob_hil.link.cia402 import codec
from dob_hil.link.cia402.codec import Command, Emcy, NmtCommand, NmtState, PowerState
from dob_hil.link.cia402.options import DEFAULT_EDS

NODE = 5


def test_controlword_commands_are_the_standard_values() -> None:
    # CiA 402 table 30: the bits each command sets (4..6, 8 zero)
    assert Command.SHUTDOWN.word == 0x06
    assert Command.SWITCH_ON.word == 0x07
    assert Command.ENABLE_OPERATION.word == 0x0F
    assert Command.DISABLE_OPERATION.word == 0x07
    assert Command.FAULT_RESET.word == 0x80
    assert Command.QUICK_STOP.word == 0x02
    assert Command.DISABLE_VOLTAGE.word == 0x00
    # the same numbers in canopen's 402 profile
    assert Command.SHUTDOWN.word == State402.CW_SHUTDOWN
    assert Command.SWITCH_ON.word == State402.CW_SWITCH_ON
    assert Command.ENABLE_OPERATION.word == State402.CW_OPERATION_ENABLED
    assert Command.QUICK_STOP.word == State402.CW_QUICK_STOP
    assert Command.DISABLE_VOLTAGE.word == State402.CW_DISABLE_VOLTAGE
    assert Command.FAULT_RESET.word == State402.CW_SWITCH_ON_DISABLED  # transition 15's word
    assert codec.fault_reset_words() == (0x00, 0x80)  # a rising edge of bit 7


CANOPEN_NAMES = {
    "NOT READY TO SWITCH ON": PowerState.NOT_READY_TO_SWITCH_ON,
    "SWITCH ON DISABLED": PowerState.SWITCH_ON_DISABLED,
    "READY TO SWITCH ON": PowerState.READY_TO_SWITCH_ON,
    "SWITCHED ON": PowerState.SWITCHED_ON,
    "OPERATION ENABLED": PowerState.OPERATION_ENABLED,
    "FAULT": PowerState.FAULT,
    "FAULT REACTION ACTIVE": PowerState.FAULT_REACTION_ACTIVE,
    "QUICK STOP ACTIVE": PowerState.QUICK_STOP_ACTIVE,
}


def test_statusword_masks_match_canopen_and_the_standard() -> None:
    for name, (mask, value) in State402.SW_MASK.items():
        assert (CANOPEN_NAMES[name].mask, CANOPEN_NAMES[name].pattern) == (mask, value)


def test_every_statusword_decodes_like_canopen() -> None:
    for word in range(0x10000):
        ours = codec.decode_state(word)
        theirs = [n for n, (mask, value) in State402.SW_MASK.items() if word & mask == value]
        assert len(theirs) <= 1
        assert ours == (CANOPEN_NAMES[theirs[0]] if theirs else None), hex(word)


@pytest.mark.parametrize(
    ("word", "state"),
    [
        (0x0250, PowerState.SWITCH_ON_DISABLED),  # with voltage, remote
        (0x0231, PowerState.READY_TO_SWITCH_ON),
        (0x0233, PowerState.SWITCHED_ON),
        (0x0237, PowerState.OPERATION_ENABLED),
        (0x0A37, PowerState.OPERATION_ENABLED),  # internal limit active, remote
        (0x0217, PowerState.QUICK_STOP_ACTIVE),
        (0x021F, PowerState.FAULT_REACTION_ACTIVE),
        (0x0218, PowerState.FAULT),
    ],
)
def test_typical_statuswords(word: int, state: PowerState) -> None:
    assert codec.decode_state(word) is state


def test_path_to_enabled_follows_figure_13() -> None:
    path = {s: codec.command_towards_enabled(s) for s in PowerState}
    assert path[PowerState.SWITCH_ON_DISABLED] is Command.SHUTDOWN
    assert path[PowerState.READY_TO_SWITCH_ON] is Command.SWITCH_ON
    assert path[PowerState.SWITCHED_ON] is Command.ENABLE_OPERATION
    assert path[PowerState.FAULT] is Command.FAULT_RESET
    assert path[PowerState.QUICK_STOP_ACTIVE] is Command.DISABLE_VOLTAGE
    assert path[PowerState.OPERATION_ENABLED] is None
    assert path[PowerState.NOT_READY_TO_SWITCH_ON] is None  # moves on its own
    assert path[PowerState.FAULT_REACTION_ACTIVE] is None
    # canopen's transition table has the same words for the same steps
    table = State402.TRANSITIONTABLE
    assert table[("SWITCH ON DISABLED", "READY TO SWITCH ON")] == Command.SHUTDOWN.word
    assert table[("READY TO SWITCH ON", "SWITCHED ON")] == Command.SWITCH_ON.word
    assert table[("SWITCHED ON", "OPERATION ENABLED")] == Command.ENABLE_OPERATION.word
    assert table[("OPERATION ENABLED", "SWITCHED ON")] == Command.DISABLE_OPERATION.word
    assert table[("OPERATION ENABLED", "QUICK STOP ACTIVE")] == Command.QUICK_STOP.word
    assert table[("FAULT", "SWITCH ON DISABLED")] == Command.FAULT_RESET.word


def test_nmt_frames_byte_for_byte() -> None:
    assert codec.encode_nmt(NmtCommand.START, NODE) == b"\x01\x05"
    assert codec.encode_nmt(NmtCommand.STOP, NODE) == b"\x02\x05"
    assert codec.encode_nmt(NmtCommand.ENTER_PRE_OPERATIONAL, NODE) == b"\x80\x05"
    assert codec.encode_nmt(NmtCommand.RESET_NODE, 0) == b"\x81\x00"
    assert codec.encode_nmt(NmtCommand.RESET_COMMUNICATION, NODE) == b"\x82\x05"
    assert NMT_COMMANDS["OPERATIONAL"] == NmtCommand.START
    assert NMT_COMMANDS["PRE-OPERATIONAL"] == NmtCommand.ENTER_PRE_OPERATIONAL
    assert NMT_COMMANDS["RESET COMMUNICATION"] == NmtCommand.RESET_COMMUNICATION
    with pytest.raises(ProtocolError, match="node id"):
        codec.encode_nmt(NmtCommand.START, 128)


def test_sync_and_heartbeat() -> None:
    assert codec.encode_sync() == b""
    assert codec.encode_sync(1) == b"\x01"
    assert codec.encode_sync(240) == b"\xf0"
    for bad in (0, 241):
        with pytest.raises(ProtocolError, match=r"1\.\.240"):
            codec.encode_sync(bad)
    assert codec.decode_heartbeat(b"\x05") is NmtState.OPERATIONAL
    assert codec.decode_heartbeat(b"\x7f") is NmtState.PRE_OPERATIONAL
    assert codec.decode_heartbeat(b"\x00") is NmtState.BOOT_UP
    assert codec.decode_heartbeat(b"\x84") is NmtState.STOPPED  # toggle bit ignored
    for bad in (b"", b"\x05\x00", b"\x03"):
        with pytest.raises(ProtocolError, match="heartbeat"):
            codec.decode_heartbeat(bad)


def test_cob_ids_are_the_predefined_connection_set() -> None:
    ids = codec.cob_ids(NODE)
    assert ids == {"EMCY": 0x085, "TPDO1": 0x185, "RPDO1": 0x205, "TPDO2": 0x285,
                   "SDO_TX": 0x585, "SDO_RX": 0x605, "HEARTBEAT": 0x705}  # fmt: skip
    node = canopen.RemoteNode(NODE, str(DEFAULT_EDS))
    assert (node.sdo.rx_cobid, node.sdo.tx_cobid) == (ids["SDO_RX"], ids["SDO_TX"])
    assert node.rpdo.map[1].predefined_cob_id == ids["RPDO1"]
    assert node.tpdo.map[1].predefined_cob_id == ids["TPDO1"]
    assert node.tpdo.map[2].predefined_cob_id == ids["TPDO2"]


@settings(deadline=None)  # a loaded CI machine: no per-example time limit
@given(st.integers(0, 0xFFFF), st.integers(0, 0xFF), st.binary(min_size=5, max_size=5))
def test_emcy_round_trip_and_canopen_agrees(code: int, register: int, manufacturer: bytes) -> None:
    data = codec.encode_emcy(Emcy(code, register, manufacturer))
    assert data == struct.pack("<HB", code, register) + manufacturer
    ours = codec.decode_emcy(data)
    consumer = EmcyConsumer()
    consumer.on_emcy(0x085, data, 0.0)
    theirs = consumer.log[-1]
    assert (ours.error_code, ours.error_register, ours.manufacturer) == (
        theirs.code,
        theirs.register,
        theirs.data,
    )


def test_emcy_description_and_bad_length() -> None:
    assert (
        codec.decode_emcy(bytes.fromhex("5082110000000000")).describe()
        == "0x8250 (RPDO timeout), register 0x11"
    )
    assert codec.decode_emcy(bytes(8)).is_reset
    assert "current" in codec.decode_emcy(bytes.fromhex("2123030000000000")).describe()
    with pytest.raises(ProtocolError, match="8 bytes"):
        codec.decode_emcy(bytes(7))


@functools.cache
def _maps() -> canopen.RemoteNode:
    """canopen's own PDO maps, mapped the way the host maps the drive (an independent decoder)."""
    node = canopen.RemoteNode(NODE, str(DEFAULT_EDS))
    rpdo, tpdo1, tpdo2 = node.rpdo.map[1], node.tpdo.map[1], node.tpdo.map[2]
    for pdo_map, objects in ((rpdo, (0x6040, 0x6071)), (tpdo1, (0x6041, 0x6064)), (tpdo2, (0x606C,))):
        pdo_map.clear()
        for index in objects:
            pdo_map.add_variable(index)
    return node


@settings(deadline=None)  # a loaded CI machine: no per-example time limit
@given(st.integers(0, 0xFFFF), st.integers(-32768, 32767))
def test_rpdo1_decoded_by_canopen(controlword: int, torque: int) -> None:
    data = codec.encode_rpdo1(controlword, torque)
    assert data == bytes((controlword & 0xFF, controlword >> 8)) + (torque & 0xFFFF).to_bytes(2, "little")
    pdo = _maps().rpdo.map[1]
    pdo.cob_id = codec.RPDO1_BASE + NODE
    pdo.on_message(pdo.cob_id, data, 0.0)
    assert pdo[0x6040].raw == controlword  # canopen's PdoMap decodes by index
    assert pdo[0x6071].raw == torque
    assert codec.decode_rpdo1(data) == (controlword, torque)


@settings(deadline=None)  # a loaded CI machine: no per-example time limit
@given(st.integers(0, 0xFFFF), st.integers(-(2**31), 2**31 - 1), st.integers(-(2**31), 2**31 - 1))
def test_tpdos_encoded_by_canopen_decode(statusword: int, position: int, velocity: int) -> None:
    node = _maps()
    tpdo1, tpdo2 = node.tpdo.map[1], node.tpdo.map[2]
    tpdo1[0x6041].raw = statusword  # canopen packs the frame the drive would send
    tpdo1[0x6064].raw = position
    tpdo2[0x606C].raw = velocity
    assert codec.decode_tpdo1(bytes(tpdo1.data)) == (statusword, position)
    assert codec.decode_tpdo2(bytes(tpdo2.data)) == velocity
    assert codec.encode_tpdo1(statusword, position) == bytes(tpdo1.data)


def test_pdo_payloads_of_the_wrong_length_are_refused() -> None:
    with pytest.raises(ProtocolError, match="TPDO1"):
        codec.decode_tpdo1(bytes(5))
    with pytest.raises(ProtocolError, match="TPDO2"):
        codec.decode_tpdo2(bytes(8))
    with pytest.raises(ProtocolError, match="RPDO1"):
        codec.decode_rpdo1(bytes(3))
    with pytest.raises(ProtocolError, match="RPDO1"):
        codec.encode_rpdo1(0x10000, 0)
