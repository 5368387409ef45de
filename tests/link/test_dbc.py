"""native.dbc agrees with the codec, both ways, for every frame type; and it ships with the package."""

from __future__ import annotations

from importlib import resources
from typing import Any

import cantools
import pytest
from hypothesis import given

from dob_hil.errors import ProtocolError
from dob_hil.link import protocol as p
from dob_hil.link.dbc import dbc_for_node, dbc_resource, dbc_text
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

from .test_protocol import any_frame


@pytest.fixture(scope="module")
def db() -> Any:
    with resources.as_file(resources.files("dob_hil.link") / "native.dbc") as path:
        return cantools.database.load_file(str(path))


def signals_of(frame: p.Frame) -> dict[str, int]:
    """The DBC signal values a frame should decode to, written from the frame table."""
    if isinstance(frame, FeedbackFrame):
        return {
            "EncoderCounts": frame.counts,
            "FeedbackSeq": frame.seq,
            "StatusEnabled": int(bool(frame.status & Status.ENABLED)),
            "StatusFault": int(bool(frame.status & Status.FAULT)),
            "StatusSaturated": int(bool(frame.status & Status.SATURATED)),
            "StatusWatchdog": int(bool(frame.status & Status.WATCHDOG)),
        }
    if isinstance(frame, CommandFrame):
        return {"CurrentCounts": frame.current_counts, "AnsweredSeq": frame.seq, "Enable": int(frame.enable)}
    if isinstance(frame, ControlFrame):
        return {"Request": int(frame.request), "ProtocolVersion": frame.version}
    if isinstance(frame, FaultFrame):
        return {"FaultCode": int(frame.code), "FaultInfo": frame.info}
    return {"DriveState": int(frame.state), "ProtocolVersion": frame.version}


def frame_of(kind: FrameKind, signals: dict[str, int]) -> p.Frame:
    if kind is FrameKind.FEEDBACK:
        status = Status(0)
        for name, bit in (
            ("StatusEnabled", Status.ENABLED),
            ("StatusFault", Status.FAULT),
            ("StatusSaturated", Status.SATURATED),
            ("StatusWatchdog", Status.WATCHDOG),
        ):
            if signals[name]:
                status |= bit
        return FeedbackFrame(signals["EncoderCounts"], signals["FeedbackSeq"], status)
    if kind is FrameKind.COMMAND:
        return CommandFrame(signals["CurrentCounts"], signals["AnsweredSeq"], bool(signals["Enable"]))
    if kind is FrameKind.CONTROL:
        return ControlFrame(ControlRequest(signals["Request"]), signals["ProtocolVersion"])
    if kind is FrameKind.FAULT:
        return FaultFrame(FaultCode(signals["FaultCode"]), signals["FaultInfo"])
    return HeartbeatFrame(DriveState(signals["DriveState"]), signals["ProtocolVersion"])


def test_dbc_ships_as_package_data() -> None:
    resource = resources.files("dob_hil.link") / "native.dbc"
    assert resource.is_file()
    assert dbc_resource().read_text(encoding="utf-8") == resource.read_text(encoding="utf-8") == dbc_text()


def test_dbc_describes_the_five_frames_of_node_1(db: Any) -> None:
    by_id = {m.frame_id: m for m in db.messages}
    assert sorted(by_id) == sorted(p.frame_id(kind, 1) for kind in FrameKind)
    for kind in FrameKind:
        message = by_id[p.frame_id(kind, 1)]
        assert message.name == kind.name
        assert message.length == p.DLC[kind]
        assert not message.is_extended_frame
        assert message.comment
        assert all(
            s.scale == 1 and s.offset == 0 and s.byte_order == "little_endian" for s in message.signals
        )
    counts = db.get_message_by_name("FEEDBACK").get_signal_by_name("EncoderCounts")
    assert counts.is_signed and counts.length == 32 and counts.unit == "counts"
    assert db.get_message_by_name("COMMAND").get_signal_by_name("CurrentCounts").is_signed


def test_dbc_enums_match_the_codec(db: Any) -> None:
    def choices(message: str, signal: str) -> dict[int, str]:
        return {
            int(k): str(v)
            for k, v in db.get_message_by_name(message).get_signal_by_name(signal).choices.items()
        }

    def camel(name: str) -> str:
        return "".join(part.capitalize() for part in name.split("_"))

    assert choices("FAULT", "FaultCode") == {int(c): camel(c.name) for c in FaultCode}
    assert choices("CONTROL", "Request") == {int(r): camel(r.name) for r in ControlRequest}
    assert choices("HEARTBEAT", "DriveState") == {int(s): camel(s.name) for s in DriveState}


@given(frame=any_frame)
def test_cantools_decodes_what_the_codec_encodes(db: Any, frame: p.Frame) -> None:
    kind, payload = p.encode(frame)
    decoded = db.decode_message(p.frame_id(kind, 1), payload, decode_choices=False)
    assert decoded == signals_of(frame)


@given(frame=any_frame)
def test_codec_decodes_what_cantools_encodes(db: Any, frame: p.Frame) -> None:
    kind, _ = p.encode(frame)
    payload = db.encode_message(p.frame_id(kind, 1), signals_of(frame))
    assert p.decode(p.frame_id(kind, 1), payload) == (1, frame_of(kind, signals_of(frame)))
    assert frame_of(kind, signals_of(frame)) == frame


def test_cantools_refuses_what_the_codec_refuses(db: Any) -> None:
    with pytest.raises(cantools.database.EncodeError):
        db.encode_message(0x6A1, {"CurrentCounts": 32768, "AnsweredSeq": 0, "Enable": 0})
    with pytest.raises(cantools.database.EncodeError):
        db.encode_message(0x681, {"FaultCode": 0, "FaultInfo": 0})


def test_dbc_carries_version_send_types_and_cycle_times(db: Any) -> None:
    """The protocol version and heartbeat period as database attributes; per frame the send type,
    the cycle time of the 100 ms HEARTBEAT in ms, and of the per-period frames in us."""
    assert db.version == f"dob_hil native {p.PROTOCOL_VERSION}"
    attributes = {name: a.value for name, a in db.dbc.attributes.items()}
    assert attributes == {
        "ProtocolVersion": p.PROTOCOL_VERSION,
        "HeartbeatPeriodMs": p.HEARTBEAT_PERIOD_NS // 10**6,
    }
    heartbeat = db.get_message_by_name("HEARTBEAT")
    assert heartbeat.cycle_time == p.HEARTBEAT_PERIOD_NS // 10**6
    assert heartbeat.send_type == "CyclicAndEvent"
    for name in ("FEEDBACK", "COMMAND"):
        message = db.get_message_by_name(name)
        assert message.send_type == "Cyclic"
        assert message.dbc.attributes["GenMsgCycleTimeUs"].value == 300
    for name in ("FAULT", "CONTROL"):
        assert db.get_message_by_name(name).send_type == "Event"
        assert db.get_message_by_name(name).cycle_time is None


def test_dbc_for_node_sets_the_cycle_time_of_another_period() -> None:
    db: Any = cantools.database.load_string(dbc_for_node(3, period_us=1000), database_format="dbc")
    assert db.get_message_by_name("FEEDBACK").dbc.attributes["GenMsgCycleTimeUs"].value == 1000
    assert db.get_message_by_name("COMMAND").frame_id == p.frame_id(FrameKind.COMMAND, 3)
    with pytest.raises(ProtocolError, match="period_us"):
        dbc_for_node(3, period_us=0)


@pytest.mark.parametrize("node", [0, 5, 9, 15])
def test_dbc_for_node_rewrites_only_the_ids(node: int) -> None:
    db: Any = cantools.database.load_string(dbc_for_node(node), database_format="dbc")
    by_id = {m.frame_id: m for m in db.messages}
    assert sorted(by_id) == sorted(p.frame_id(kind, node) for kind in FrameKind)
    for kind in FrameKind:
        message = by_id[p.frame_id(kind, node)]
        assert message.name == kind.name
        assert message.comment  # CM_ BO_ lines follow the new ids
    feedback = FeedbackFrame(-123456, 42, Status.ENABLED)
    _, payload = p.encode(feedback)
    assert db.decode_message(
        p.frame_id(FrameKind.FEEDBACK, node), payload, decode_choices=False
    ) == signals_of(feedback)
    choices = db.get_message_by_name("HEARTBEAT").get_signal_by_name("DriveState").choices
    assert choices is not None and len(choices) == 3  # VAL_ lines follow the new ids


def test_dbc_for_node_1_is_the_shipped_file() -> None:
    assert dbc_for_node(1) == dbc_text()


@pytest.mark.parametrize("node", [-1, 16, 128])
def test_dbc_for_node_refuses_bad_node_ids(node: int) -> None:
    with pytest.raises(ProtocolError, match=f"node_id: the native protocol has nodes 0..15, got {node}"):
        dbc_for_node(node)
