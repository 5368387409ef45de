"""NativeDriveLink.receive_feedback decodes the common FEEDBACK delivered (the per-period path); it
must give the same Feedback, link state, statistics and events as ``_on_feedback`` (the general
decoder it shortcuts) on every kind of feedback sequence."""

from __future__ import annotations

import random
import struct
from collections import deque

import can
from twin_links import assert_same_link_state

from dob_hil.config import DriveConfig
from dob_hil.link.base import LinkEvent
from dob_hil.link.native import NativeDriveLink
from dob_hil.link.protocol import FrameKind, Status
from dob_hil.loop.inproc_bus import InProcessBus

ENABLED = int(Status.ENABLED)
SAT = int(Status.SATURATED)
FAULT = int(Status.FAULT)


def _link(inbox: deque[can.Message], events: list[LinkEvent]) -> NativeDriveLink:
    bus = InProcessBus("t", inbox, deque())
    return NativeDriveLink(
        bus, DriveConfig(encoder_bits=16), event_hook=events.append, clock_ns=lambda: 42, owns_bus=True
    )


def _feedback_stream(n: int) -> list[can.Message]:
    """FEEDBACK frames of node 1: mostly the next sequence number and a small step; now and then
    saturated, a gap, a duplicate, an older one, an implausible step, a wrap of the 16-bit counter,
    a padded frame, a status with FAULT or reserved bits, DISABLED."""
    rng = random.Random(4)
    fid = FrameKind.FEEDBACK + 1
    seq, counts = 0, 0
    out = []
    for _ in range(n):
        r = rng.random()
        status = ENABLED | (SAT if rng.random() < 0.2 else 0)
        step = rng.randint(-300, 300)
        if r < 0.03:
            seq = (seq + rng.randint(2, 5)) % 256  # a gap
        elif r < 0.05:
            pass  # a duplicate sequence number
        elif r < 0.06:
            seq = (seq - 3) % 256  # older
        else:
            seq = (seq + 1) % 256
        if 0.06 <= r < 0.08:
            step = rng.choice((-1, 1)) * 20000  # beyond a quarter of the 16-bit range
        if 0.08 <= r < 0.09:
            status = rng.choice((FAULT, 0, ENABLED | 0x40))  # FAULT, DISABLED, a reserved bit
        counts = (counts + step + 2**15) % 2**16 - 2**15
        payload = struct.pack("<iBB", counts, seq, status)
        if 0.09 <= r < 0.1:
            payload += bytes(2)  # padded to 8 bytes
        out.append(can.Message(arbitration_id=fid, data=payload, is_extended_id=False))
    return out


def test_delivered_feedback_matches_on_feedback() -> None:
    inbox: deque[can.Message] = deque()
    ev_fast: list[LinkEvent] = []
    ev_general: list[LinkEvent] = []
    fast = _link(inbox, ev_fast)
    general = _link(deque(), ev_general)
    delivered = 0
    for msg in _feedback_stream(5000):
        before = fast.stats.feedback
        inbox.append(msg)
        got = fast.receive_feedback(0)
        want = general._on_feedback(msg, 42)
        assert got == want
        fields = ("_last_seq", "_state", "_resync", "_last_fault")
        assert_same_link_state(fast, general, fields, ev_fast, ev_general)
        delivered += fast.stats.feedback - before
    assert fast.stats.rx_frames == 5000
    assert fast.stats.encoder_jumps > 0 and fast.stats.stale_feedback > 0 and fast.stats.missed_feedback > 0
    assert delivered > 4000
    fast.close()
    general.close()


def test_positional_frames_equal_keyword_frames() -> None:
    """The per-period paths build can.Message positionally (dob_hil.link.base checks the order at
    import); such a frame is the keyword-built one in every attribute."""
    import inspect

    from dob_hil.link.base import MESSAGE_LEADING_PARAMS

    assert tuple(inspect.signature(can.Message.__init__).parameters)[1:9] == MESSAGE_LEADING_PARAMS
    data = bytes([1, 2, 3, 4, 5, 6])
    a = can.Message(0.0, 0x181, False, False, False, None, None, data)
    b = can.Message(arbitration_id=0x181, data=data, is_extended_id=False)
    assert a.equals(b, timestamp_delta=None, check_channel=True, check_direction=True)
    slots = [s for cls in type(a).__mro__ for s in getattr(cls, "__slots__", ())]
    assert [getattr(a, s) for s in slots] == [getattr(b, s) for s in slots]
