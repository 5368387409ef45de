"""dob_hil.link.message.data_frame: the same python-can message as the constructor, slot for slot."""

from __future__ import annotations

import can
import pytest

from dob_hil.link import message
from dob_hil.link.message import MESSAGE_SLOTS, data_frame, message_slots

CASES = [
    (0.0, 0x181, b"\x37\x06\x10\x27\x00\x00"),
    (0.0, 0x80, b""),
    (12.5e-3, 0x7FF, bytes(range(8))),
    (1.0, 0x0, bytearray(b"\x01\x02")),
]


def _slots(msg: can.Message) -> dict[str, object]:
    return {name: getattr(msg, name) for name in MESSAGE_SLOTS}


def test_the_slots_it_sets_are_python_cans() -> None:
    assert message_slots() == MESSAGE_SLOTS
    assert data_frame is message._built  # the fast builder is the one in use with this python-can


@pytest.mark.parametrize("build", [message._built, message._constructed])
@pytest.mark.parametrize(("timestamp", "arbitration_id", "data"), CASES)
def test_equal_to_the_constructor(build: object, timestamp: float, arbitration_id: int, data: bytes) -> None:
    built = build(timestamp, arbitration_id, data)  # type: ignore[operator]
    reference = can.Message(timestamp, arbitration_id, False, False, False, None, None, data)
    assert type(built) is can.Message
    assert _slots(built) == _slots(reference)
    assert type(built.data) is bytearray and built.dlc == len(data)
    assert built.equals(reference, timestamp_delta=0.0)
    reference._check()  # python-can's own checks of a valid message
    built._check()


def test_the_message_holds_a_copy_of_the_payload() -> None:
    payload = bytearray(b"\x01\x02")
    msg = data_frame(0.0, 0x201, payload)
    payload[0] = 9
    assert msg.data == bytearray(b"\x01\x02")


def test_a_python_can_with_other_slots_gets_the_constructor() -> None:
    assert message.builder(MESSAGE_SLOTS) is message._built
    assert message.builder(MESSAGE_SLOTS | {"priority"}) is message._constructed  # a slot added
    assert message.builder(MESSAGE_SLOTS - {"is_rx"}) is message._constructed  # one gone
    assert message.builder(frozenset()) is message._constructed  # no slots: attributes in __dict__
