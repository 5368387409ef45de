"""Several axes of the native protocol on one bus: one :class:`~dob_hil.link.base.DriveLink`.

Axis i is node ``node_ids[i]`` (:func:`dob_hil.link.axes.axis_node_ids`), plant input i and plant
output i. Each axis is a :class:`~dob_hil.link.native.NativeDriveLink` (every rule of
``docs/PROTOCOL.md`` for one node: validation, sequence, unwrapping, DAC quantizing and limiting,
enable and stop sequences), composed here over one bus:

* **Routing.** One reader (:class:`BusRouter`) reads the bus and hands every frame of an axis's
  node to that axis's queue (:class:`AxisBus`, the bus the axis's link sees); the axis's link
  reads its queue as it would the bus, reading the shared bus on when its queue is empty (its
  receipt time is when it reads the frame, in the same receive call as the router). Frames
  of no axis's node (other nodes, other ids, 29-bit ids, remote and error frames) go to the frame
  hook and are reported here (FOREIGN_FRAME, ERROR_FRAME).
* **One feedback per period.** :meth:`MultiAxisNativeLink.receive_feedback` collects each axis's
  FEEDBACK by sequence number and returns one :class:`~dob_hil.link.base.Feedback` with every
  axis's counts once every axis's FEEDBACK of the same period has arrived; it never mixes periods.
  A period still incomplete when a newer one completes, or for longer than the host timeout
  (``drive.feedback_timeout_periods`` periods after its first FEEDBACK), is missing (a
  STALE_FEEDBACK event, ``stats.incomplete_periods``); its late frames are discarded as stale, as
  is feedback older than the last period delivered. A period completed late (an axis's frame
  delayed, within the timeout) is delivered late, as one drive's late feedback is.
* **Commands.** :meth:`quantize` quantizes and limits each axis's current with that axis's DAC and
  the configured limit; :meth:`send_command` sends one COMMAND per axis answering the period.
* **All or nothing.** enable / enable_lockstep / safe_stop / close act on every axis; an axis that
  fails to enable stops every axis; an axis in FAULT makes :meth:`receive_feedback` raise
  :class:`~dob_hil.errors.DriveFault` (the session then stops every axis at zero current and
  disabled), as does a host timeout.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Final

import can

from dob_hil.config import DriveConfig
from dob_hil.errors import DriveFault, ProtocolError
from dob_hil.link.axes import axis_node_ids
from dob_hil.link.base import EventHook, Feedback, FrameHook, LinkEvent, LinkEventKind
from dob_hil.link.native import (
    DEFAULT_STALE_WINDOW,
    MAX_CONSECUTIVE_RX_ERRORS,
    DacQuantizer,
    LinkStats,
    NativeDriveLink,
)
from dob_hil.link.protocol import ID_FIRST, ID_LAST

MAX_QUEUED_PER_AXIS: Final = 4096  # frames kept for an axis that does not read (oldest dropped)
MAX_OPEN_PERIODS: Final = 8  # incomplete periods kept at once (the oldest is missing beyond)
_SEQ_HALF: Final = 128


def _newer(seq: int, than: int) -> bool:
    """``seq`` is 1..127 sequence numbers ahead of ``than`` (mod 256)."""
    return 0 < (seq - than) & 0xFF < _SEQ_HALF


def _describe(msg: can.Message) -> str:
    if msg.is_error_frame:
        return f"(error class 0x{msg.arbitration_id:X}, data {bytes(msg.data).hex() or '-'})"
    width = 8 if msg.is_extended_id else 3
    return f"id 0x{msg.arbitration_id:0{width}X} DLC {msg.dlc} data {bytes(msg.data).hex() or '-'}"


@dataclass(slots=True)
class AxesStats:
    """What the multi-axis link saw besides each axis's :class:`~dob_hil.link.native.LinkStats`."""

    periods: int = 0  # complete periods delivered
    incomplete_periods: int = 0  # periods with some axes' FEEDBACK missing
    stale_feedback: int = 0  # an axis's FEEDBACK of a period already delivered or given up
    foreign_frames: int = 0
    error_frames: int = 0
    rx_errors: int = 0
    queue_overflows: int = 0  # frames dropped from an axis queue nobody read
    axes: list[LinkStats] = field(default_factory=list)


class BusRouter:
    """Reads the shared bus and routes each frame to the queue of its axis (module docstring)."""

    def __init__(
        self,
        bus: can.BusABC,
        node_ids: tuple[int, ...],
        stats: AxesStats,
        frame_hook: FrameHook | None,
        event: Callable[[LinkEventKind, str], None],
    ) -> None:
        self.bus = bus
        self.node_ids = node_ids
        self.inboxes: list[deque[can.Message]] = [deque() for _ in node_ids]
        self._axis_of_node = {node: i for i, node in enumerate(node_ids)}
        self._stats = stats
        self._frame_hook = frame_hook
        self._event = event
        self._errors_in_row = 0

    def route(self, msg: can.Message) -> int | None:
        """The axis of ``msg``; None for a frame of no axis (reported here)."""
        if msg.is_error_frame:
            self._own(msg)
            self._stats.error_frames += 1
            self._event(LinkEventKind.ERROR_FRAME, f"CAN error frame {_describe(msg)}")
            return None
        aid = msg.arbitration_id
        axis = None
        if not msg.is_extended_id and not msg.is_remote_frame and ID_FIRST <= aid <= ID_LAST:
            axis = self._axis_of_node.get(aid & 0x0F)
        if axis is None:
            self._own(msg)
            self._stats.foreign_frames += 1
            what = "29-bit id " if msg.is_extended_id else "remote frame " if msg.is_remote_frame else ""
            self._event(
                LinkEventKind.FOREIGN_FRAME,
                f"{what}{_describe(msg)} is no frame of nodes {list(self.node_ids)}",
            )
        return axis

    def _own(self, msg: can.Message) -> None:
        if self._frame_hook is not None:
            self._frame_hook(msg, True)

    def _queue(self, axis: int, msg: can.Message) -> None:
        inbox = self.inboxes[axis]
        if len(inbox) >= MAX_QUEUED_PER_AXIS:
            inbox.popleft()
            self._stats.queue_overflows += 1
        inbox.append(msg)

    def recv_for(self, axis: int, timeout_s: float | None) -> can.Message | None:
        """The next frame of ``axis`` from the bus (others queued for their axes), or None after
        ``timeout_s`` (0: only what is queued). ``CanError`` propagates to the axis's link."""
        deadline_s = None if timeout_s is None else time.monotonic() + timeout_s
        wait_s = timeout_s
        while True:
            msg = self.bus.recv(wait_s)
            if msg is None:
                return None
            target = self.route(msg)
            if target == axis:
                return msg
            if target is not None:
                self._queue(target, msg)
            if deadline_s is not None:
                wait_s = max(0.0, deadline_s - time.monotonic())

    def wait(self, timeout_s: float) -> bool:
        """Read one frame from the bus (blocking up to ``timeout_s``) and route it; False if none."""
        try:
            msg = self.bus.recv(timeout_s)
        except can.CanError as exc:
            self._stats.rx_errors += 1
            self._errors_in_row += 1
            self._event(LinkEventKind.MALFORMED_FRAME, f"the bus could not deliver a received frame: {exc}")
            if self._errors_in_row >= MAX_CONSECUTIVE_RX_ERRORS:
                raise DriveFault(
                    f"receiving from the CAN bus failed {self._errors_in_row} times in a row"
                ) from exc
            return True
        self._errors_in_row = 0
        if msg is None:
            return False
        target = self.route(msg)
        if target is not None:
            self._queue(target, msg)
        return True


class AxisBus(can.BusABC):
    """The bus one axis's link sees: its own queue in, the shared bus out. Never shut down by the axis."""

    def __init__(self, router: BusRouter, axis: int) -> None:
        self.channel_info = f"axis {axis} (node {router.node_ids[axis]}) of {router.bus.channel_info}"
        self._router = router
        self._axis = axis
        self._inbox = router.inboxes[axis]
        super().__init__(channel=f"axis-{axis}")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._router.bus.send(msg, timeout)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        if self._inbox:
            return self._inbox.popleft()
        return self._router.recv_for(self._axis, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.recv(timeout), False


class MultiAxisNativeLink:
    """N native drive nodes on one bus, one axis each (see the module docstring)."""

    def __init__(
        self,
        bus: can.BusABC,
        drive: DriveConfig,
        n_axes: int,
        *,
        frame_hook: FrameHook | None = None,
        event_hook: EventHook | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        owns_bus: bool = False,
        stale_window: int = DEFAULT_STALE_WINDOW,
        send_timeout_ns: int | None = None,
        period_ns: int | None = None,
    ) -> None:
        """``period_ns``: the control period, for the host timeout of an incomplete period
        (``drive.feedback_timeout_periods * period_ns``; None: only a newer period ends it)."""
        self.node_ids = axis_node_ids(drive, n_axes)
        self.n_axes = n_axes
        self._drive = drive
        self._bus = bus
        self._owns_bus = owns_bus
        self._event_hook = event_hook
        self._clock_ns = clock_ns
        self.stats = AxesStats()
        self._router = BusRouter(bus, self.node_ids, self.stats, frame_hook, self._event)
        self._axis_buses = [AxisBus(self._router, i) for i in range(n_axes)]
        self.axes = [
            NativeDriveLink(
                self._axis_buses[i],
                replace(drive, node_id=node, node_ids=None),
                frame_hook=frame_hook,
                event_hook=event_hook,
                clock_ns=clock_ns,
                stale_window=stale_window,
                send_timeout_ns=send_timeout_ns,
            )
            for i, node in enumerate(self.node_ids)
        ]
        self.stats.axes = [axis.stats for axis in self.axes]
        self._open: dict[int, list[Feedback | None]] = {}  # seq -> each axis's feedback, oldest first
        self._opened_ns: dict[int, int] = {}  # seq -> receipt time of its first FEEDBACK
        self._partial_timeout_ns = None if period_ns is None else drive.feedback_timeout_periods * period_ns
        self._floor_seq: int | None = None  # the newest period delivered or given up
        self._closed = False

    # --- properties ------------------------------------------------------------------------------
    @property
    def current_limit_A(self) -> float:
        return self._drive.current_limit_A

    @property
    def max_current_A(self) -> float:
        return self.axes[0].max_current_A

    @property
    def faulted(self) -> bool:
        return any(axis.faulted for axis in self.axes)

    @property
    def fault_description(self) -> str | None:
        """The fault of the first axis that reported one (naming its node), or None."""
        for axis in self.axes:
            text = axis.fault_description
            if text is not None and axis.faulted:
                return f"node {axis.node_id}: {text}"
        return None

    @property
    def closed(self) -> bool:
        return self._closed

    def _event(self, kind: LinkEventKind, message: str) -> None:
        if self._event_hook is not None:
            self._event_hook(LinkEvent(self._clock_ns(), kind, message))

    # --- receiving -------------------------------------------------------------------------------
    def receive_feedback(self, timeout_ns: int) -> Feedback | None:
        """Every axis's feedback of the next complete period, or None once ``timeout_ns`` passed."""
        if self._closed:
            raise DriveFault("the multi-axis drive link is closed")
        deadline_ns = time.monotonic_ns() + timeout_ns if timeout_ns > 0 else 0
        while True:
            for i, axis in enumerate(self.axes):
                while (fb := axis.receive_feedback(0)) is not None:
                    self._collect(i, fb)
            self._check_faults()
            done = self._take_complete()
            if done is not None:
                return done
            self._expire()
            if not deadline_ns:
                return None
            remaining_ns = deadline_ns - time.monotonic_ns()
            if remaining_ns <= 0:
                return None
            self._router.wait(remaining_ns * 1e-9)

    def _expire(self) -> None:
        """Give up the periods incomplete for longer than the host timeout."""
        limit = self._partial_timeout_ns
        if limit is None or not self._open:
            return
        now_ns = self._clock_ns()
        old = [seq for seq, t in self._opened_ns.items() if now_ns - t > limit]
        if old:
            self._give_up(old, f"past the host timeout of {limit / 1e6:g} ms")

    def _check_faults(self) -> None:
        for axis in self.axes:
            if axis.faulted:
                raise DriveFault(
                    f"node {axis.node_id} reports a fault: {axis.fault_description or 'code unknown'}; "
                    f"every axis (nodes {list(self.node_ids)}) is stopped"
                )

    def _collect(self, axis: int, fb: Feedback) -> None:
        seq = fb.seq
        slot = self._open.get(seq)
        if slot is None:
            if self._floor_seq is not None and not _newer(seq, self._floor_seq):
                self.stats.stale_feedback += 1
                self._event(
                    LinkEventKind.STALE_FEEDBACK,
                    f"node {self.node_ids[axis]}: feedback seq {seq} of a period already delivered "
                    f"or given up (last {self._floor_seq}), discarded",
                )
                return
            if len(self._open) >= MAX_OPEN_PERIODS:
                self._give_up([next(iter(self._open))], "too many periods open")
            slot = self._open[seq] = [None] * self.n_axes
            self._opened_ns[seq] = fb.rx_time_ns
        slot[axis] = fb

    def _take_complete(self) -> Feedback | None:
        for seq, slot in self._open.items():
            if all(f is not None for f in slot):
                older = []
                for s in self._open:
                    if s == seq:
                        break
                    older.append(s)
                self._give_up(older, f"period {seq} completed first")
                del self._open[seq], self._opened_ns[seq]
                self._floor_seq = seq
                self.stats.periods += 1
                return _combine(seq, [f for f in slot if f is not None])
        return None

    def _give_up(self, seqs: list[int], why: str) -> None:
        for seq in seqs:
            slot = self._open.pop(seq)
            del self._opened_ns[seq]
            missing = [self.node_ids[i] for i, f in enumerate(slot) if f is None]
            self.stats.incomplete_periods += 1
            if self._floor_seq is None or _newer(seq, self._floor_seq):
                self._floor_seq = seq
            self._event(
                LinkEventKind.STALE_FEEDBACK,
                f"feedback seq {seq} incomplete ({why}): no FEEDBACK of node(s) {missing}; "
                "the period counts as missing",
            )

    def _reset_periods(self) -> None:
        self._open.clear()
        self._opened_ns.clear()
        self._floor_seq = None

    # --- quantizing and sending --------------------------------------------------------------------
    def quantize(self, current_A: tuple[float, ...]) -> tuple[tuple[int, ...], tuple[float, ...], bool]:
        """Each axis's current quantized and limited by that axis: (codes, applied, any saturated)."""
        if len(current_A) != self.n_axes:
            raise ProtocolError(f"current_A: {self.n_axes} axes, got {len(current_A)} currents")
        codes: list[int] = []
        applied: list[float] = []
        saturated = False
        for axis, u in zip(self.axes, current_A, strict=True):
            (code,), (a,), sat = axis.quantize((u,))
            codes.append(code)
            applied.append(a)
            saturated = saturated or sat
        return tuple(codes), tuple(applied), saturated

    def send_command(self, codes: tuple[int, ...], answers_seq: int) -> int:
        """One COMMAND per axis answering period ``answers_seq``; returns clock_ns()."""
        if len(codes) != self.n_axes:
            raise ProtocolError(f"COMMAND.current_counts: {self.n_axes} axes, got {len(codes)} codes")
        for axis, code in zip(self.axes, codes, strict=True):
            axis.send_command((code,), answers_seq)
        return self._clock_ns()

    # --- enable, stop ------------------------------------------------------------------------------
    def enable(self, timeout_ns: int) -> None:
        """Enable every axis: CONTROL enable to every node at once, then each as
        :meth:`NativeDriveLink.enable` (ClearFault first with ``drive.clear_fault``, the request
        repeated until its node reports enabled); any failure stops every axis."""
        deadline_ns = time.monotonic_ns() + timeout_ns
        self._reset_periods()
        try:
            if not self._drive.clear_fault:
                for axis in self.axes:  # every node at once; enable() below repeats and waits
                    axis.request_enable()
            for axis in self.axes:
                axis.enable(max(deadline_ns - time.monotonic_ns(), 1))
        except BaseException:
            self.safe_stop()
            raise
        self._reset_periods()

    def enable_lockstep(self, service: Callable[[], int], max_rounds: int = 3) -> None:
        """Enable every axis against the embedded lockstep drive: all requests, then ``service()``
        until every axis reported enabled; DriveFault (every axis stopped) if one does not."""
        self._reset_periods()
        try:
            if self._drive.clear_fault:
                for axis in self.axes:
                    axis.request_clear_fault()
                service()
                for axis in self.axes:  # read what each node said (a FAULT sent before, its new state)
                    while axis.receive_feedback(0) is not None:
                        pass
            for axis in self.axes:
                axis.request_enable()
            for _ in range(max_rounds):
                service()
                if all([axis.poll_enabled() for axis in self.axes]):
                    return
            off = [axis.node_id for axis in self.axes if not axis.poll_enabled()]
            raise DriveFault(f"node(s) {off} of the simulated drive did not report enabled")
        except BaseException:
            self.safe_stop()
            raise

    def safe_stop(self) -> None:
        """Zero current and disable on every axis (each axis's stop sequence). Never raises."""
        for axis in self.axes:
            axis.safe_stop()

    def close(self) -> None:
        """safe_stop() on every axis, then shut the bus down if this link owns it. Safe to call twice."""
        if self._closed:
            return
        try:
            for axis in self.axes:
                axis.close()
        finally:
            self._closed = True
            for bus in self._axis_buses:
                bus.shutdown()
            if self._owns_bus:
                self._bus.shutdown()

    def __enter__(self) -> MultiAxisNativeLink:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def axes_quantizer(
    drive: DriveConfig,
) -> Callable[[tuple[float, ...]], tuple[tuple[int, ...], tuple[float, ...], bool]]:
    """The link's :meth:`~MultiAxisNativeLink.quantize` as a pure function of the drive config, for
    any number of axes (each axis :class:`~dob_hil.link.native.DacQuantizer` on its own current;
    one axis: exactly ``DacQuantizer.quantize``), for ``dob-hil replay``."""
    one = DacQuantizer(drive).quantize

    def quantize(current_A: tuple[float, ...]) -> tuple[tuple[int, ...], tuple[float, ...], bool]:
        if len(current_A) == 1:
            return one(current_A)
        codes: list[int] = []
        applied: list[float] = []
        saturated = False
        for u in current_A:
            (code,), (a,), sat = one((u,))
            codes.append(code)
            applied.append(a)
            saturated = saturated or sat
        return tuple(codes), tuple(applied), saturated

    return quantize


def _combine(seq: int, per_axis: list[Feedback]) -> Feedback:
    return Feedback(
        max(f.rx_time_ns for f in per_axis),
        seq,
        tuple(f.raw_counts[0] for f in per_axis),
        tuple(f.counts[0] for f in per_axis),
        tuple(f.position[0] for f in per_axis),
        all(f.enabled for f in per_axis),
        any(f.fault for f in per_axis),
        any(f.saturated for f in per_axis),
    )


__all__ = ["AxesStats", "AxisBus", "BusRouter", "MultiAxisNativeLink", "axes_quantizer"]
