"""The conformance kit's host side on the bus: records the drive's frames and answers its feedback.

:class:`Probe` runs one receive thread on a python-can bus. It keeps every frame of the drive under
test (its FAULT, FEEDBACK and HEARTBEAT ids) with its arrival time, and, in an answering mode,
sends a COMMAND from that thread the moment a FEEDBACK arrives (as a host's loop would):

* ``answer``: the feedback just received (a valid command);
* ``late``: the feedback before it (one period late: valid for an accept window of 2 or more);
* ``repeat``: always the same, already answered sequence number (a duplicate: stale);
* ``off``: nothing.

Waiting is counted in the drive's own periods (FEEDBACK frames received), with a wall-clock cap,
so that a loaded machine stretches a check instead of failing it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import can

from dob_hil.errors import ProtocolError
from dob_hil.link import protocol
from dob_hil.link.protocol import (
    MAX_PADDED_LEN,
    PROTOCOL_VERSION,
    ControlFrame,
    ControlRequest,
    FrameKind,
    frame_id,
)

RECV_POLL_S = 0.05


@dataclass(frozen=True)
class Rx:
    """One frame of the drive under test, as received."""

    index: int
    t_ns: int  # time.monotonic_ns() at receipt
    kind: FrameKind
    data: bytes
    frame: protocol.Frame | None  # None: it does not decode (the reason is in ``problem``)
    problem: str = ""


class Probe:
    def __init__(self, bus: can.BusABC, node_id: int) -> None:
        self.bus = bus
        self.node_id = node_id
        self.kind_of = {
            frame_id(k, node_id): k for k in (FrameKind.FAULT, FrameKind.FEEDBACK, FrameKind.HEARTBEAT)
        }
        self.command_id = frame_id(FrameKind.COMMAND, node_id)
        self.control_id = frame_id(FrameKind.CONTROL, node_id)
        self.frames: list[Rx] = []
        self.rx_errors = 0
        self.mode = "off"
        self.current_counts = 0
        self.enable_bit = True
        self.repeat_seq = 0
        self.commands_sent = 0
        self.last_answered: int | None = None  # sequence number of the last feedback answered
        self._prev_seq: int | None = None
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._send_lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="conformance-rx", daemon=True)

    # --- life cycle ------------------------------------------------------------------------------
    def __enter__(self) -> Probe:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.mode = "off"
        self._stop.set()
        self._thread.join(5.0)

    # --- sending ---------------------------------------------------------------------------------
    def send(self, arbitration_id: int, payload: bytes) -> None:
        with self._send_lock:
            self.bus.send(can.Message(arbitration_id=arbitration_id, data=payload, is_extended_id=False))

    def control(self, request: ControlRequest, *, version: int = PROTOCOL_VERSION, pad: bytes = b"") -> None:
        payload = protocol.encode_control(ControlFrame(request, version))
        self.send(self.control_id, (payload + pad)[:MAX_PADDED_LEN])

    def command(self, current_counts: int, seq: int, enable: bool) -> None:
        payload = protocol.encode_command(protocol.CommandFrame(current_counts, seq % 128, enable))
        self.send(self.command_id, payload)
        self.commands_sent += 1

    def set_mode(self, mode: str, *, current_counts: int = 0, enable: bool = True) -> None:
        with self._cond:
            self.current_counts = current_counts
            self.enable_bit = enable
            if mode == "repeat":
                self.repeat_seq = self.last_answered if self.last_answered is not None else 0
            self.mode = mode

    # --- reading ---------------------------------------------------------------------------------
    def mark(self) -> int:
        with self._cond:
            return len(self.frames)

    def since(self, mark: int, kind: FrameKind | None = None) -> list[Rx]:
        with self._cond:
            got = self.frames[mark:]
        return [f for f in got if kind is None or f.kind is kind]

    def wait(
        self, mark: int, predicate: Callable[[Rx], bool], *, periods: int, timeout_s: float
    ) -> Rx | None:
        """The first frame since ``mark`` that satisfies ``predicate``; None once ``periods``
        feedback frames (the drive's periods) or ``timeout_s`` seconds passed without one."""
        deadline = time.monotonic() + timeout_s
        seen = mark
        feedbacks = 0
        with self._cond:
            while True:
                while seen < len(self.frames):
                    rx = self.frames[seen]
                    seen += 1
                    if predicate(rx):
                        return rx
                    if rx.kind is FrameKind.FEEDBACK:
                        feedbacks += 1
                        if feedbacks >= periods:
                            return None
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._cond.wait(min(remaining, 0.05))

    def periods(self, n: int, timeout_s: float) -> int:
        """Wait for ``n`` more feedback frames (or ``timeout_s``); how many came."""
        mark = self.mark()
        self.wait(mark, lambda rx: False, periods=n, timeout_s=timeout_s)
        return len(self.since(mark, FrameKind.FEEDBACK))

    # --- the receive thread ------------------------------------------------------------------------
    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self.bus.recv(RECV_POLL_S)
            except can.CanError:
                self.rx_errors += 1
                continue
            if msg is None or msg.is_error_frame or msg.is_extended_id or msg.is_remote_frame:
                continue
            kind = self.kind_of.get(msg.arbitration_id)
            if kind is None:
                continue
            now = time.monotonic_ns()
            data = bytes(msg.data)
            try:
                _, frame = protocol.decode(msg.arbitration_id, data)
                problem = ""
            except ProtocolError as exc:
                frame, problem = None, str(exc)
            if isinstance(frame, protocol.FeedbackFrame):
                self._answer(frame.seq)
            with self._cond:
                self.frames.append(Rx(len(self.frames), now, kind, data, frame, problem))
                self._cond.notify_all()

    def _answer(self, seq: int) -> None:
        mode = self.mode
        try:
            if mode == "answer":
                self.command(self.current_counts, seq, self.enable_bit)
                self.last_answered = seq
            elif mode == "late" and self._prev_seq is not None:
                self.command(self.current_counts, self._prev_seq, self.enable_bit)
                self.last_answered = self._prev_seq
            elif mode == "repeat":
                self.command(self.current_counts, self.repeat_seq, self.enable_bit)
        except (can.CanError, ProtocolError):
            pass  # a send that failed shows as a missing command: the rule that needed it fails
        self._prev_seq = seq
