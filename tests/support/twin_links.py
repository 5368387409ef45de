"""Checks shared by the tests of a link's inline receive path against its general decoder.

A link's ``receive_feedback`` decodes the per-period feedback frame inline; a twin link fed the
same frame through the general decoder must end in the same state: the named fields, the
position unwrapper, every statistic (but ``rx_frames``: the twin's decoder is called directly,
not through a receive) and the events, in order.
"""

from __future__ import annotations

from typing import Any

from dob_hil.link.base import LinkEvent


def assert_same_link_state(
    fast: Any,
    general: Any,
    fields: tuple[str, ...],
    events_fast: list[LinkEvent],
    events_general: list[LinkEvent],
) -> None:
    assert [getattr(fast, f) for f in fields] == [getattr(general, f) for f in fields], fields
    assert (fast._unwrapper._last, fast._unwrapper._position) == (
        general._unwrapper._last,
        general._unwrapper._position,
    )
    names = [k for k in type(fast.stats).__slots__ if k != "rx_frames"]
    assert {k: getattr(fast.stats, k) for k in names} == {k: getattr(general.stats, k) for k in names}
    assert [(e.kind, e.message) for e in events_fast] == [(e.kind, e.message) for e in events_general]
