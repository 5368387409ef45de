"""An in-process CAN bus for lockstep: python-can's ``BusABC`` without the copies of ``virtual``.

Lockstep runs the host and the embedded simulated drive in one thread, so a bus only has to hand a
frame from one end to the other. python-can's ``virtual`` interface deep-copies every message and
takes a lock for it (about 30 us of a 70 us lockstep sample, mostly ``deepcopy``); this one appends
the sender's :class:`can.Message` to the other end's queue. Frames stay python-can messages and go
through the same codecs. The receiver gets the sender's object: safe, since nothing in the project
changes a message once sent (the senders build a fresh one per send, except frames that never
change, such as the CiA 402 link's SYNC without counter, built once). Not thread-safe by design:
real-time runs with the embedded drive use ``virtual``.

:func:`bus_pair` returns the two ends; ``interface="virtual"`` in the session options selects
python-can's bus instead (``RunOptions.bus_impl``).
"""

from __future__ import annotations

from collections import deque

import can

from dob_hil.errors import DobHilError

BUS_IMPLS = ("inprocess", "virtual")


class InProcessBus(can.BusABC):
    """One end of a point-to-point in-process bus (see the module docstring)."""

    def __init__(self, channel: str, inbox: deque[can.Message], outbox: deque[can.Message]) -> None:
        self.channel_info = f"in-process bus {channel}"
        self._inbox = inbox
        self._outbox = outbox
        super().__init__(channel=channel)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self._is_shutdown:
            raise can.CanOperationError("the in-process bus is shut down")
        self._outbox.append(msg)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The next frame, or None at once if none is queued (one thread: nothing can arrive while
        this end waits, so a timeout would only waste time). Without filters an end receives
        through :meth:`_recv_any` (bound in :meth:`_apply_filters`)."""
        inbox = self._inbox
        while inbox:
            msg = inbox.popleft()
            if self._filters is None or self._matches_filters(msg):
                return msg
        return None

    def _recv_any(self, timeout: float | None = None) -> can.Message | None:
        """:meth:`recv` of an end without filters: the next frame, or None."""
        inbox = self._inbox
        return inbox.popleft() if inbox else None

    def _apply_filters(self, filters: can.typechecking.CanFilters | None) -> None:
        # python-can's set_filters (also from BusABC.__init__) stores them in _filters first
        if filters is None:
            self.recv = self._recv_any  # type: ignore[method-assign]
        else:
            self.__dict__.pop("recv", None)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        inbox = self._inbox
        return (inbox.popleft() if inbox else None), False

    def shutdown(self) -> None:
        self._inbox.clear()
        super().shutdown()


def bus_pair(channel: str, impl: str = "inprocess") -> tuple[can.BusABC, can.BusABC]:
    """(host end, drive end) of a lockstep bus: ``inprocess`` (default) or python-can ``virtual``."""
    if impl == "inprocess":
        a_to_b: deque[can.Message] = deque()
        b_to_a: deque[can.Message] = deque()
        return InProcessBus(channel, b_to_a, a_to_b), InProcessBus(channel, a_to_b, b_to_a)
    if impl == "virtual":
        return (
            can.Bus(interface="virtual", channel=channel, receive_own_messages=False),
            can.Bus(interface="virtual", channel=channel, receive_own_messages=False),
        )
    raise DobHilError(f"--bus-impl: expected one of {', '.join(BUS_IMPLS)}, got {impl!r}")
