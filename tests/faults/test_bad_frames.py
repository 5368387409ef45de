"""Arbitrary frames into the host's receive path: only the documented outcomes, never a Feedback
from a frame that is not a valid FEEDBACK of our node."""

from __future__ import annotations

import collections
from typing import Any

import can
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dob_hil.config import DriveConfig
from dob_hil.link import protocol
from dob_hil.link.base import LinkEvent
from dob_hil.link.native import NativeDriveLink
from dob_hil.link.protocol import FrameKind

NODE = 5
FB_ID = FrameKind.FEEDBACK + NODE


class QueueBus(can.BusABC):
    """A bus whose received frames are a list given by the test; sends are kept."""

    def __init__(self, frames: list[can.Message]) -> None:
        self.rx = collections.deque(frames)
        self.sent: list[can.Message] = []
        super().__init__(channel="queue")

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return (self.rx.popleft() if self.rx else None), False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append(msg)


_std_ids = st.one_of(
    st.integers(0, 0x7FF),
    st.sampled_from([FB_ID, FrameKind.FEEDBACK + 1, FrameKind.FAULT + NODE, FrameKind.HEARTBEAT + NODE,
                     FrameKind.COMMAND + NODE, FrameKind.CONTROL + NODE]),
)  # fmt: skip


@st.composite
def frames(draw: Any) -> can.Message:
    kind = draw(st.sampled_from(["std", "std", "std", "ext", "remote", "error", "fd"]))
    if kind == "fd":
        data = draw(st.binary(min_size=0, max_size=64))
        return can.Message(
            arbitration_id=draw(_std_ids), is_extended_id=False, is_fd=True, data=data, check=False
        )
    data = draw(st.binary(min_size=0, max_size=8))
    if kind == "ext":
        return can.Message(arbitration_id=draw(st.integers(0, 0x1FFFFFFF)), is_extended_id=True, data=data)
    if kind == "remote":
        return can.Message(arbitration_id=draw(_std_ids), is_extended_id=False, is_remote_frame=True,
                           dlc=draw(st.integers(0, 8)))  # fmt: skip
    if kind == "error":
        return can.Message(arbitration_id=draw(st.integers(0, 0x1FFFFFFF)), is_error_frame=True, data=data)
    return can.Message(arbitration_id=draw(_std_ids), is_extended_id=False, data=data)


def _valid_feedback(msg: can.Message) -> bool:
    if (
        msg.arbitration_id != FB_ID
        or msg.is_extended_id
        or msg.is_remote_frame
        or msg.is_error_frame
        or msg.is_fd
    ):
        return False
    try:
        protocol.decode_feedback(bytes(msg.data))
    except protocol.ProtocolError:
        return False
    return True


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow], database=None)
@given(st.lists(frames(), min_size=1, max_size=40))
def test_arbitrary_frames_never_give_a_wrong_feedback(msgs: list[can.Message]) -> None:
    bus = QueueBus(msgs)
    seen: list[can.Message] = []
    events: list[LinkEvent] = []
    link = NativeDriveLink(
        bus, DriveConfig(node_id=NODE), frame_hook=lambda m, rx: seen.append(m) if rx else None,
        event_hook=events.append, owns_bus=True,
    )  # fmt: skip
    delivered = 0
    while True:
        fb = link.receive_feedback(0)  # documented: Feedback or None; DriveFault only for bus errors
        if fb is None:
            break
        delivered += 1
        source = seen[-1]  # the frame handed to the hook just before the feedback was returned
        assert _valid_feedback(source)
        frame = protocol.decode_feedback(bytes(source.data))
        assert (fb.seq, fb.raw_counts) == (frame.seq, (frame.counts,))
    link.close()
    assert len(seen) == len(msgs)  # every frame was read (and handed to the log)
    assert delivered <= sum(_valid_feedback(m) for m in msgs)
    # everything skipped that is not our own echo or plain stale/valid feedback is an event
    for m in msgs:
        if m.is_error_frame:
            assert any(e.kind.value == "error_frame" for e in events)
