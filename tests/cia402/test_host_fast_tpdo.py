"""Cia402DriveLink.receive_feedback decodes the common TPDO1 inline (the per-period path); it must
give the same Feedback, link state, statistics and events as ``_on_tpdo1`` (the general decoder
it shortcuts) on every kind of TPDO1 sequence."""

from __future__ import annotations

import random
import struct
from collections import deque

import can
from host_peer import FAULT, OE, QSA, SO
from twin_links import assert_same_link_state

from dob_hil.config import load_config
from dob_hil.link.base import LinkEvent
from dob_hil.link.cia402.link import Cia402DriveLink
from dob_hil.loop.inproc_bus import InProcessBus
from dob_hil.scenarios import scenario_path

INTERNAL_LIMIT = 0x0800
TPDO1 = 0x181


def _link(inbox: deque[can.Message], events: list[LinkEvent]) -> Cia402DriveLink:
    config = load_config(scenario_path("paper-step-cia402"))
    return Cia402DriveLink(
        InProcessBus("t", inbox, deque()),
        config,
        event_hook=events.append,
        clock_ns=lambda: 42,
        owns_bus=True,
    )


def _stream(n: int) -> list[tuple[can.Message, bool]]:
    """(TPDO1, answers a pending SYNC?) pairs: mostly OPERATION ENABLED and a small step; now and
    then the internal limit bit, another state, a wrap of the 32-bit counter, an implausible
    step, a wrong length, an unsolicited (stale) frame."""
    rng = random.Random(7)
    counts = 2**31 - 2000
    out = []
    for _ in range(n):
        r = rng.random()
        sw = OE | (INTERNAL_LIMIT if rng.random() < 0.2 else 0)
        step = rng.randint(-500, 500)
        if r < 0.03:
            sw = rng.choice((FAULT, QSA, SO, 0x0008 | 0x0027))  # other states, a fault bit
        elif r < 0.05:
            step = rng.choice((-1, 1)) * 2**30  # beyond the plausibility bound
        counts = (counts + step + 2**31) % 2**32 - 2**31
        payload = struct.pack("<Hi", sw, counts)
        if 0.05 <= r < 0.06:
            payload = payload[:5]  # malformed
        out.append(
            (can.Message(arbitration_id=TPDO1, data=payload, is_extended_id=False), not 0.06 <= r < 0.08)
        )
    return out


def test_the_inline_tpdo1_matches_on_tpdo1() -> None:
    inbox: deque[can.Message] = deque()
    ev_fast: list[LinkEvent] = []
    ev_general: list[LinkEvent] = []
    fast = _link(inbox, ev_fast)
    general = _link(deque(), ev_general)
    general_calls = 0
    on_tpdo1 = fast._on_tpdo1

    def counted(msg: can.Message, now_ns: int) -> object:
        nonlocal general_calls
        general_calls += 1
        return on_tpdo1(msg, now_ns)

    fast._on_tpdo1 = counted  # type: ignore[method-assign,assignment]
    delivered = 0
    for msg, awaited in _stream(5000):
        for link in (fast, general):  # what send_trigger does
            link._awaiting_tpdo = awaited
            link.stats.syncs += 1
        before = fast.stats.feedback
        inbox.append(msg)
        got = fast.receive_feedback(0)
        want = general._on_tpdo1(msg, 42)
        assert got == want
        fields = ("_awaiting_tpdo", "_statusword", "_state")
        assert_same_link_state(fast, general, fields, ev_fast, ev_general)
        delivered += fast.stats.feedback - before
    assert fast.stats.rx_frames == 5000
    assert fast.stats.encoder_jumps > 0 and fast.stats.stale_feedback > 0 and fast.stats.malformed_frames > 0
    assert delivered > 4000
    assert general_calls < 2000  # the rest (most) took the inline path
    fast.close()
    general.close()
