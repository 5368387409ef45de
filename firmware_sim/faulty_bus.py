"""FaultyBus: a python-can bus wrapper that injects transport faults, seeded and deterministic.

Wrap either end of a bus (the host's, through ``RunOptions.bus_wrapper``, or the drive's)::

    plan = FaultPlan(rx_match=0x181, drop_probability=0.01, seed=3)
    bus = FaultyBus(can.Bus(interface="virtual", channel="x"), plan)

Received frames whose id is ``rx_match`` (every frame when None; error frames never) may be,
each decided with its own seeded random stream (so enabling one fault does not reshuffle another):

* dropped (``drop_probability``);
* delayed (``delay_probability``): held back until ``delay_frames`` later matching frames have been
  delivered, then delivered right after the last of them; ``delay_frames=1`` swaps it with the next
  one (reordered), ``delay_frames=2`` makes it two periods late for a periodic frame;
* corrupted (``corrupt_probability``): XORed with ``corrupt_xor`` (cycled over the payload), or
  with random bytes when ``corrupt_xor`` is empty;
* given a wrong length (``dlc_probability``): cut to a random shorter length (padding up to 8
  bytes is no fault: the protocol allows it);
* duplicated (``duplicate_probability``): delivered twice in a row.

After every ``inject_every``-th matching frame the next frame of ``inject`` (cycled) is delivered
too: frames with unknown ids, of other nodes, error frames. The order of the checks is drop, delay,
corrupt, DLC, duplicate.

Sending: the ``send_fail_at``-th frame (0-based) whose id is ``tx_match`` (every frame when None)
and the ``send_fail_count - 1`` sends after it, of any id (None: every later send: bus off), raise
:class:`can.CanOperationError` with ``send_fail_message``. ``send_drop_at``/``send_drop_count`` do
the same but silently: ``send`` returns and the frame never reaches the bus (a lost transmission).

Every fault injected is appended to :attr:`FaultyBus.record` as ``(kind, index, arbitration_id)``,
``index`` counting matching received frames (rx faults) or matching sends (tx faults) from 0.
"""

from __future__ import annotations

import collections
import random
import time
from dataclasses import dataclass, field
from typing import Any

import can

RX_KINDS = ("drop", "delay", "corrupt", "dlc", "duplicate")


@dataclass(frozen=True)
class FaultPlan:
    seed: int = 0
    rx_match: int | None = None
    drop_probability: float = 0.0
    delay_probability: float = 0.0
    delay_frames: int = 1
    corrupt_probability: float = 0.0
    corrupt_xor: bytes = b""
    dlc_probability: float = 0.0
    duplicate_probability: float = 0.0
    inject_every: int = 0
    inject: tuple[can.Message, ...] = ()
    tx_match: int | None = None
    send_fail_at: int | None = None
    send_fail_count: int | None = 1
    send_fail_message: str = "Transmit buffer full"
    send_drop_at: int | None = None
    send_drop_count: int | None = 1

    def __post_init__(self) -> None:
        for name in ("drop", "delay", "corrupt", "dlc", "duplicate"):
            p = getattr(self, f"{name}_probability")
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name}_probability must be in [0, 1], got {p}")
        if self.delay_frames < 1:
            raise ValueError(f"delay_frames must be >= 1, got {self.delay_frames}")
        if self.inject_every < 0 or (self.inject_every and not self.inject):
            raise ValueError("inject_every must be >= 0, and needs frames in inject")


@dataclass
class _Held:
    msg: can.Message
    remaining: int  # matching frames still to be delivered before this one


@dataclass
class _Window:
    at: int | None
    count: int | None
    active_left: int | None = field(default=None)  # sends left in the window once it started
    started: bool = False

    def hit(self, index: int | None) -> bool:
        """Whether this send is in the window; ``index`` is the matching send's index (None: no match)."""
        if not self.started:
            if self.at is None or index is None or index < self.at:
                return False
            self.started = True
            self.active_left = self.count
        if self.active_left is None:
            return True
        if self.active_left <= 0:
            return False
        self.active_left -= 1
        return True


class FaultyBus(can.BusABC):
    """Wraps ``inner`` (which it owns: :meth:`shutdown` shuts it down). See the module docstring."""

    def __init__(self, inner: can.BusABC, plan: FaultPlan, **kwargs: Any) -> None:
        self.inner = inner
        self.plan = plan
        self.record: list[tuple[str, int, int]] = []
        self.rx_index = 0  # matching frames received from the inner bus
        self.tx_index = 0  # matching sends
        self._rng = {kind: random.Random(f"faulty_bus/{kind}/{plan.seed}") for kind in (*RX_KINDS, "data")}
        self._ready: collections.deque[can.Message] = collections.deque()
        self._held: list[_Held] = []
        self._inject_next = 0
        self._fail = _Window(plan.send_fail_at, plan.send_fail_count)
        self._drop = _Window(plan.send_drop_at, plan.send_drop_count)
        super().__init__(channel=getattr(inner, "channel_info", "faulty"), **kwargs)
        self.channel_info = f"faulty({getattr(inner, 'channel_info', '?')})"

    def counts(self) -> collections.Counter[str]:
        return collections.Counter(kind for kind, _, _ in self.record)

    # --- receiving -----------------------------------------------------------------------------
    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._ready:
            return self._ready.popleft(), False
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            msg = self.inner.recv(left)
            if msg is None:
                return None, False
            self._process(msg)
            if self._ready:
                return self._ready.popleft(), False
            # the frame was dropped or held back: read on within the same timeout

    def _draw(self, kind: str) -> bool:
        p: float = getattr(self.plan, f"{kind}_probability")
        return p > 0.0 and self._rng[kind].random() < p

    def _process(self, msg: can.Message) -> None:
        plan = self.plan
        if msg.is_error_frame or (plan.rx_match is not None and msg.arbitration_id != plan.rx_match):
            self._ready.append(msg)
            return
        index = self.rx_index
        self.rx_index += 1
        aid = msg.arbitration_id
        if self._draw("drop"):
            self.record.append(("drop", index, aid))
            self._after_matching(None)
            return
        if self._draw("delay"):
            self.record.append(("delay", index, aid))
            self._held.append(_Held(msg, plan.delay_frames))
            self._after_matching(None)
            return
        if self._draw("corrupt"):
            self.record.append(("corrupt", index, aid))
            msg = self._corrupt(msg)
        if self._draw("dlc"):
            self.record.append(("dlc", index, aid))
            msg = self._change_dlc(msg)
        self._ready.append(msg)
        if self._draw("duplicate"):
            self.record.append(("duplicate", index, aid))
            self._ready.append(_copy(msg, msg.data))
        self._after_matching(msg)

    def _after_matching(self, delivered: can.Message | None) -> None:
        """A matching frame was handled: release held frames whose turn has come, inject frames."""
        if delivered is not None and self._held:
            still: list[_Held] = []
            for held in self._held:
                held.remaining -= 1
                if held.remaining <= 0:
                    self._ready.append(held.msg)
                else:
                    still.append(held)
            self._held = still
        plan = self.plan
        if plan.inject_every and self.rx_index % plan.inject_every == 0:
            frame = plan.inject[self._inject_next % len(plan.inject)]
            self._inject_next += 1
            kind = "inject_error" if frame.is_error_frame else "inject"
            self.record.append((kind, self.rx_index - 1, frame.arbitration_id))
            self._ready.append(_copy(frame, frame.data))

    def _corrupt(self, msg: can.Message) -> can.Message:
        data = bytearray(msg.data)
        pattern = self.plan.corrupt_xor
        rng = self._rng["data"]
        for i in range(len(data)):
            data[i] ^= pattern[i % len(pattern)] if pattern else rng.randrange(1, 256)
        return _copy(msg, bytes(data))

    def _change_dlc(self, msg: can.Message) -> can.Message:
        rng = self._rng["data"]
        n = len(msg.data)
        if n == 0:
            return msg
        return _copy(msg, bytes(msg.data[: rng.randrange(n)]))

    # --- sending -------------------------------------------------------------------------------
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        plan = self.plan
        index: int | None = None
        if plan.tx_match is None or msg.arbitration_id == plan.tx_match:
            index = self.tx_index
            self.tx_index += 1
        if self._fail.hit(index):
            self.record.append(("send_fail", self.tx_index - 1, msg.arbitration_id))
            raise can.CanOperationError(plan.send_fail_message)
        if self._drop.hit(index):
            self.record.append(("send_drop", self.tx_index - 1, msg.arbitration_id))
            return
        self.inner.send(msg, timeout)

    def shutdown(self) -> None:
        try:
            self.inner.shutdown()
        finally:
            super().shutdown()


def _copy(msg: can.Message, data: bytes | bytearray) -> can.Message:
    return can.Message(
        timestamp=msg.timestamp,
        arbitration_id=msg.arbitration_id,
        is_extended_id=msg.is_extended_id,
        is_remote_frame=msg.is_remote_frame,
        is_error_frame=msg.is_error_frame,
        is_fd=msg.is_fd,
        dlc=len(data) if not msg.is_remote_frame else msg.dlc,
        data=data,
        channel=msg.channel,
        check=False,
    )


__all__ = ["RX_KINDS", "FaultPlan", "FaultyBus"]
