"""The native codec: exact bytes, round trips, range errors, malformed frames, arbitrary input."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dob_hil.errors import ProtocolError
from dob_hil.link import protocol as p
from dob_hil.link.protocol import (
    CommandFrame,
    ControlFrame,
    ControlRequest,
    DriveState,
    FaultCode,
    FaultFrame,
    FeedbackFrame,
    FrameKind,
    HeartbeatFrame,
    Status,
)

# --- exact bytes (worked by hand from the frame table) ----------------------------------------------
VECTORS: list[tuple[p.Frame, FrameKind, str]] = [
    # 0x12345678 little endian, seq 0xAB, status ENABLED|SATURATED = 0x05
    (FeedbackFrame(0x12345678, 0xAB, Status.ENABLED | Status.SATURATED), FrameKind.FEEDBACK, "78563412ab05"),
    # -2 = 0xFFFFFFFE, seq 0, no status bits
    (FeedbackFrame(-2, 0, Status(0)), FrameKind.FEEDBACK, "feffffff0000"),
    # most negative counts, seq 255, FAULT|WATCHDOG = 0x0A
    (FeedbackFrame(-(2**31), 255, Status.FAULT | Status.WATCHDOG), FrameKind.FEEDBACK, "00000080ff0a"),
    # -1433 = 0xFA67 -> 67 FA; seq 5 with the enable bit: 0x85
    (CommandFrame(-1433, 5, True), FrameKind.COMMAND, "67fa85"),
    # 1433 = 0x0599 -> 99 05; seq 127, enable clear: 0x7F
    (CommandFrame(1433, 127, False), FrameKind.COMMAND, "99057f"),
    (CommandFrame(-32768, 0, True), FrameKind.COMMAND, "008080"),
    # request, then the protocol version (2)
    (ControlFrame(ControlRequest.DISABLE), FrameKind.CONTROL, "0002"),
    (ControlFrame(ControlRequest.ENABLE), FrameKind.CONTROL, "0102"),
    (ControlFrame(ControlRequest.CLEAR_FAULT), FrameKind.CONTROL, "0202"),
    (ControlFrame(ControlRequest.ENABLE, 1), FrameKind.CONTROL, "0101"),  # another version decodes as sent
    (FaultFrame(FaultCode.WATCHDOG, 10), FrameKind.FAULT, "010a"),
    (FaultFrame(FaultCode.BAD_FRAME, 0x81), FrameKind.FAULT, "0481"),
    # state, then the protocol version
    (HeartbeatFrame(DriveState.DISABLED), FrameKind.HEARTBEAT, "0002"),
    (HeartbeatFrame(DriveState.FAULT), FrameKind.HEARTBEAT, "0202"),
    (HeartbeatFrame(DriveState.ENABLED, 3), FrameKind.HEARTBEAT, "0103"),
]


@pytest.mark.parametrize(("frame", "kind", "hex_bytes"), VECTORS)
def test_exact_bytes(frame: p.Frame, kind: FrameKind, hex_bytes: str) -> None:
    assert p.encode(frame) == (kind, bytes.fromhex(hex_bytes))
    assert p.decode(p.frame_id(kind, 1), bytes.fromhex(hex_bytes)) == (1, frame)


def test_ids_follow_the_function_base_plus_node() -> None:
    assert [p.frame_id(k, 1) for k in FrameKind] == [0x681, 0x691, 0x6A1, 0x6B1, 0x6C1]
    assert p.frame_id(FrameKind.HEARTBEAT, 15) == 0x6CF == p.ID_LAST
    assert p.frame_id(FrameKind.FAULT, 0) == 0x680 == p.ID_FIRST
    assert p.split_id(0x6A5) == (FrameKind.COMMAND, 5)
    with pytest.raises(ProtocolError, match=r"node_id: the native protocol has nodes 0\.\.15, got 16"):
        p.frame_id(FrameKind.FEEDBACK, 16)


# CiA 301's predefined connection set and restricted CAN-IDs (NMT, SYNC/EMCY, TIME, PDOs, SDOs,
# NMT error control, LSS and the reserved ranges): no native id may be one of them
CANOPEN_IDS = (
    {0x000, 0x080, 0x100}
    | set(range(0x001, 0x080))  # restricted
    | set(range(0x081, 0x100))  # EMCY
    | set(range(0x101, 0x181))  # restricted
    | set(range(0x181, 0x580))  # TPDO1..4 / RPDO1..4
    | set(range(0x580, 0x680))  # SDO server->client, client->server
    | set(range(0x6E0, 0x800))  # restricted, NMT error control (heartbeat, boot-up), LSS
)


def test_no_id_collides_with_canopen_predefined_connection_set() -> None:
    ours = {p.frame_id(kind, node) for kind in FrameKind for node in range(p.NODE_ID_MAX + 1)}
    assert len(ours) == len(FrameKind) * (p.NODE_ID_MAX + 1)
    assert ours.isdisjoint(CANOPEN_IDS)
    assert min(ours) == p.ID_FIRST and max(ours) == p.ID_LAST


# --- hypothesis round trips for every frame type ---------------------------------------------------
feedback_frames = st.builds(
    FeedbackFrame,
    counts=st.integers(p.COUNTS_MIN, p.COUNTS_MAX),
    seq=st.integers(0, 255),
    status=st.integers(0, 15).map(Status),
)
command_frames = st.builds(
    CommandFrame,
    current_counts=st.integers(p.CURRENT_COUNTS_MIN, p.CURRENT_COUNTS_MAX),
    seq=st.integers(0, 127),
    enable=st.booleans(),
)
versions = st.one_of(st.just(p.PROTOCOL_VERSION), st.integers(0, 255))  # decoded as sent
control_frames = st.builds(ControlFrame, request=st.sampled_from(ControlRequest), version=versions)
fault_frames = st.builds(FaultFrame, code=st.sampled_from(FaultCode), info=st.integers(0, 255))
heartbeat_frames = st.builds(HeartbeatFrame, state=st.sampled_from(DriveState), version=versions)
any_frame = st.one_of(feedback_frames, command_frames, control_frames, fault_frames, heartbeat_frames)


@given(frame=any_frame, node=st.integers(0, 15))
def test_round_trip_every_frame_type(frame: p.Frame, node: int) -> None:
    kind, payload = p.encode(frame)
    assert len(payload) == p.DLC[kind]
    assert p.decode(p.frame_id(kind, node), payload) == (node, frame)


@given(frame=feedback_frames)
def test_feedback_round_trip(frame: FeedbackFrame) -> None:
    assert p.decode_feedback(p.encode_feedback(frame)) == frame


@given(frame=command_frames)
def test_command_round_trip(frame: CommandFrame) -> None:
    decoded = p.decode_command(p.encode_command(frame))
    assert decoded == frame
    assert p.seq_answers(decoded.seq, frame.seq + 128)


@given(frame=st.one_of(control_frames, fault_frames, heartbeat_frames))
def test_state_frames_round_trip(frame: p.Frame) -> None:
    kind, payload = p.encode(frame)
    assert p.decode(p.frame_id(kind, 3), bytearray(payload)) == (3, frame)
    assert p.decode(p.frame_id(kind, 3), memoryview(payload)) == (3, frame)


# --- encode: out of range names signal, limit and value -----------------------------------------------
@pytest.mark.parametrize(
    ("frame", "signal", "limit", "value"),
    [
        (FeedbackFrame(2**31, 0, Status(0)), "FEEDBACK.counts", "2147483647", "2147483648"),
        (FeedbackFrame(-(2**31) - 1, 0, Status(0)), "FEEDBACK.counts", "-2147483648", "-2147483649"),
        (FeedbackFrame(0, 256, Status(0)), "FEEDBACK.seq", "0..255", "256"),
        (FeedbackFrame(0, -1, Status(0)), "FEEDBACK.seq", "0..255", "-1"),
        (FeedbackFrame(0, 0, 0x10), "FEEDBACK.status", "0..15", "16"),  # type: ignore[arg-type]
        (CommandFrame(32768, 0, True), "COMMAND.current_counts", "-32768..32767", "32768"),
        (CommandFrame(-32769, 0, True), "COMMAND.current_counts", "-32768..32767", "-32769"),
        (CommandFrame(0, 128, True), "COMMAND.seq", "0..127", "128"),
        (FaultFrame(FaultCode.ENCODER, 256), "FAULT.info", "0..255", "256"),
        (FaultFrame(9, 0), "FAULT.code", "6 (HOST_REQUEST)", "9"),  # type: ignore[arg-type]
        (ControlFrame(3), "CONTROL.request", "2 (CLEAR_FAULT)", "3"),  # type: ignore[arg-type]
        (HeartbeatFrame(7), "HEARTBEAT.state", "2 (FAULT)", "7"),  # type: ignore[arg-type]
    ],
)
def test_encode_out_of_range_names_signal_limit_value(
    frame: p.Frame, signal: str, limit: str, value: str
) -> None:
    with pytest.raises(ProtocolError) as info:
        p.encode(frame)
    text = str(info.value)
    assert text.startswith(f"{signal}: ")
    assert limit in text
    assert value in text


@pytest.mark.parametrize(
    ("frame", "signal"),
    [
        (FeedbackFrame(1.5, 0, Status(0)), "FEEDBACK.counts"),  # type: ignore[arg-type]
        (CommandFrame(True, 0, False), "COMMAND.current_counts"),
        (FaultFrame("x", 0), "FAULT.code"),  # type: ignore[arg-type]
    ],
)
def test_encode_rejects_non_integers(frame: p.Frame, signal: str) -> None:
    with pytest.raises(ProtocolError, match=f"^{signal}: expected an integer"):
        p.encode(frame)


# --- saturation is its own step ---------------------------------------------------------------------
def test_saturate_current_counts_clamps_symmetrically() -> None:
    assert p.saturate_current_counts(1434, 1433) == 1433
    assert p.saturate_current_counts(-32768, 1433) == -1433
    assert p.saturate_current_counts(1433, 1433) == 1433
    assert p.saturate_current_counts(-1433, 1433) == -1433
    assert p.saturate_current_counts(17, 1433) == 17


@given(code=st.integers(-(2**20), 2**20), limit=st.integers(0, 32767))
def test_saturate_is_the_nearest_code_within_the_limit(code: int, limit: int) -> None:
    out = p.saturate_current_counts(code, limit)
    assert -limit <= out <= limit
    assert out == min(max(code, -limit), limit)
    # encoding the saturated code never fails, and encoding is not where clamping happens
    assert p.decode_command(p.encode_command(CommandFrame(out, 0, True))).current_counts == out


def test_encode_does_not_clamp() -> None:
    with pytest.raises(ProtocolError, match=r"COMMAND\.current_counts"):
        p.encode_command(CommandFrame(40000, 0, True))


# --- decode: wrong DLC, reserved bits, unknown codes ---------------------------------------------------
@pytest.mark.parametrize("kind", list(FrameKind))
@pytest.mark.parametrize("length", [-1, 9])
def test_decode_wrong_length(kind: FrameKind, length: int) -> None:
    data = bytes(p.DLC[kind] - 1 if length < 0 else length)
    with pytest.raises(ProtocolError) as info:
        p.decode(p.frame_id(kind, 1), data)
    assert str(info.value).startswith(
        f"{kind.name} frame: expected {p.DLC[kind]} bytes (padding up to 8 allowed), got {len(data)}"
    )


@given(frame=any_frame, padding=st.binary(max_size=8))
def test_padded_frames_decode_to_the_same_frame(frame: p.Frame, padding: bytes) -> None:
    kind, payload = p.encode(frame)
    padded = (payload + padding)[:8]
    assert p.decode(p.frame_id(kind, 2), padded) == (2, frame)


def test_decode_empty_payload() -> None:
    with pytest.raises(ProtocolError, match=r"HEARTBEAT frame: expected 2 bytes .*, got 0 byte\(s\) -"):
        p.decode(0x6C1, b"")


@pytest.mark.parametrize("status", [0x10, 0x20, 0x80, 0xF1])
def test_decode_feedback_reserved_bits(status: int) -> None:
    with pytest.raises(ProtocolError, match=f"reserved status bits set \\(0x{status:02X}\\)"):
        p.decode_feedback(bytes([0, 0, 0, 0, 0, status]))


@pytest.mark.parametrize(
    ("frame_id", "payload", "match"),
    [
        (0x691, b"\x03\x02", "CONTROL frame: unknown request 3"),
        (0x681, b"\x00\x00", "FAULT frame: unknown fault code 0"),
        (0x681, b"\x07\x00", "FAULT frame: unknown fault code 7"),
        (0x6C1, b"\x03\x02", "HEARTBEAT frame: unknown drive state 3"),
        (0x100, b"", "id 0x100: not a frame of the native protocol"),
        (0x7FF, b"", "id 0x7FF: not a frame of the native protocol"),
        (0x701, b"\x00", "id 0x701: not a frame of the native protocol"),  # version 1's heartbeat
        (0x181, bytes(6), "id 0x181: not a frame of the native protocol"),  # version 1's feedback
        (0x800, b"", "id 0x800: not an 11-bit id"),
        (-1, b"", "not an 11-bit id"),
    ],
)
def test_decode_unknown_codes_and_ids(frame_id: int, payload: bytes, match: str) -> None:
    with pytest.raises(ProtocolError, match=match):
        p.decode(frame_id, payload)


@given(arbitration_id=st.integers(-(2**12), 2**30), data=st.binary(max_size=16))
def test_decode_arbitrary_input_returns_a_frame_or_raises_protocol_error(
    arbitration_id: int, data: bytes
) -> None:
    try:
        node, frame = p.decode(arbitration_id, data)
    except ProtocolError:
        return
    # whatever decodes is a canonical frame: it encodes back to the same id and bytes (the
    # padding of a padded frame aside)
    kind, payload = p.encode(frame)
    assert p.frame_id(kind, node) == arbitration_id
    assert payload == data[: len(payload)] and len(data) <= 8


@given(kind=st.sampled_from(FrameKind), node=st.integers(0, 15), data=st.binary(min_size=0, max_size=8))
def test_decode_arbitrary_payload_of_our_ids(kind: FrameKind, node: int, data: bytes) -> None:
    try:
        got_node, frame = p.decode(p.frame_id(kind, node), data)
    except ProtocolError as exc:
        assert kind.name in str(exc)
        return
    assert got_node == node
    assert p.encode(frame) == (kind, data[: p.DLC[kind]])
