"""The ground-truth datagram: documented layout, byte for byte, and hypothesis round trips."""

from __future__ import annotations

import socket
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dob_hil.errors import ProtocolError
from dob_hil.link.protocol import DriveState
from firmware_sim.truth import TRUTH_HEADER_SIZE, GroundTruth, UdpTruthSender, decode_truth, encode_truth


def test_layout_byte_for_byte() -> None:
    t = GroundTruth(7, 2_100_000, (1.5, -2.0), 0.25, -0.5, DriveState.FAULT)
    expected = (
        b"FSGT"
        + bytes([1, 2])
        + (2).to_bytes(2, "little")
        + (7).to_bytes(8, "little")
        + (2_100_000).to_bytes(8, "little", signed=True)
        + struct.pack("<d", 0.25)
        + struct.pack("<d", -0.5)
        + struct.pack("<dd", 1.5, -2.0)
    )
    assert TRUTH_HEADER_SIZE == 40
    assert encode_truth(t) == expected
    assert decode_truth(expected) == t


finite = st.floats(allow_nan=False, allow_infinity=True)


truths = st.builds(
    GroundTruth,
    st.integers(0, 2**64 - 1),
    st.integers(-(2**63), 2**63 - 1),
    st.lists(finite, max_size=12).map(tuple),
    finite,
    finite,
    st.sampled_from(list(DriveState)),
)


@given(truths)
def test_round_trip(truth: GroundTruth) -> None:
    assert decode_truth(encode_truth(truth)) == truth


@pytest.mark.parametrize(
    ("data", "problem"),
    [
        (b"FSGT\x01", "expected >= 40 bytes"),
        (b"XXXX" + bytes(36), "bad magic"),
        (b"FSGT\x02" + bytes(35), "version 2"),
        (b"FSGT\x01\x00\x01\x00" + bytes(32), "1 states need 48 bytes, got 40"),
        (b"FSGT\x01\x07\x00\x00" + bytes(32), "unknown drive state 7"),
    ],
)
def test_malformed_datagrams_are_refused(data: bytes, problem: str) -> None:
    with pytest.raises(ProtocolError, match=problem):
        decode_truth(data)


def test_udp_sender_never_raises_without_a_listener() -> None:
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    sender = UdpTruthSender(port)
    t = GroundTruth(1, 300_000, (0.0, 1.0), 0.0, 0.0, DriveState.ENABLED)
    sender(t)
    probe.settimeout(2.0)
    assert decode_truth(probe.recv(4096)) == t
    probe.close()
    for _ in range(3):
        sender(t)  # nobody listening any more: counted, not raised
    sender.close()
    with pytest.raises(ValueError, match=r"1\.\.65535"):
        UdpTruthSender(0)
