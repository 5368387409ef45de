"""The native drive profile: :class:`~dob_hil.link.base.DriveLink` over a python-can bus.

One drive (``drive.node_id``, 0..15), one axis. The frames are those of
:mod:`dob_hil.link.protocol` (version 2); ``docs/PROTOCOL.md`` is the contract this module keeps
on the host's side. This module adds the transport: receiving and validating, unwrapping the
encoder counter, quantizing and limiting the current, sending, and the enable/stop sequences.

Receiving. :meth:`NativeDriveLink.receive_feedback` blocks in ``bus.recv`` (it never spins) until
a valid FEEDBACK of our node arrives. Everything else that arrives on the way is handed to
``frame_hook(msg, True)`` and then reported to ``event_hook`` and skipped: error frames
(ERROR_FRAME), remote frames, 29-bit ids, other nodes' frames and ids of no native frame
(FOREIGN_FRAME), our ids with a payload that does not decode (MALFORMED_FRAME; frames padded up
to 8 bytes decode), a datagram or frame the bus itself could not deliver (``bus.recv`` raising
``CanError``: MALFORMED_FRAME, after :data:`MAX_CONSECUTIVE_RX_ERRORS` in a row a DriveFault),
a HEARTBEAT of another protocol version (MALFORMED_FRAME; an enable attempt then fails naming
both versions), FEEDBACK whose sequence number is a duplicate or up to ``stale_window`` behind
the last accepted one (STALE_FEEDBACK). The first FEEDBACK that reports ENABLED after a state
other than ENABLED starts a new sequence (a drive may restart its counter on enable). FAULT
frames give DRIVE_FAULT, heartbeats (and feedback status bits) that change the drive state give
DRIVE_STATE. Our own COMMAND and CONTROL ids coming back (``udp_multicast``
delivers a process its own frames even with ``receive_own_messages=False``) are skipped silently
and only counted in :attr:`NativeDriveLink.stats`; they never reach the controller.

Time. ``Feedback.rx_time_ns`` and every ``LinkEvent.time_ns`` is ``clock_ns()`` read right
after ``bus.recv`` returned the frame (host receipt time, ``time.monotonic_ns`` by default; a
lockstep runner passes its simulated clock). The bus's own timestamp stays in ``msg.timestamp``
for the log. Timeouts (``timeout_ns`` arguments) are wall-clock, measured with
``time.monotonic_ns``, because ``bus.recv`` blocks in wall-clock time. A timeout of 0 still
reads every frame already queued, so a lockstep caller that services the simulated drive before
receiving gets its frames.

Quantizing. ``code = clamp(round_half_away(u / dac_lsb_A), -L, +L)`` with
``L = floor(current_limit_A / dac_lsb_A)``, so the applied current ``code * dac_lsb_A`` never
exceeds the limit (0.7 A and 1/2048 A give L = 1433, 0.69970703125 A). Rounding is half away from
zero (``lround`` of C firmware), not Python's half-to-even ``round``: it is odd-symmetric and has
no dependence on the parity of the code. A non-finite current (NaN, inf) gives code 0 (0 A),
``saturated=True`` and an event: the drive is never told anything but a finite, limited current.

Enabling. :meth:`~NativeDriveLink.enable` = :meth:`~NativeDriveLink.request_enable` +
:meth:`~NativeDriveLink.wait_enabled`. In lockstep (the caller services the simulated drive
between send and receive) use the split form: ``request_enable()``, then service the drive and
call :meth:`~NativeDriveLink.poll_enabled` (non-blocking) until it returns True. An enable
attempt succeeds when a HEARTBEAT or FEEDBACK received after the request shows the drive enabled;
a FAULT frame, or a drive that reports FAULT (it refuses to enable until a ClearFault), or a
HEARTBEAT of another protocol version during the attempt raises :class:`~dob_hil.errors.DriveFault`
naming the fault code and info, the frames rejected, and the remedy (``--clear-fault``).
:meth:`~NativeDriveLink.clear_fault` sends ClearFault and waits for the drive to leave FAULT.

Stopping. :meth:`~NativeDriveLink.safe_stop` sends one stop sequence: a zero-current COMMAND with
the enable bit clear answering the newest feedback received (so the drive accepts it as valid; it
is sent only to a drive last reported ENABLED or in FAULT, never to one reported DISABLED or not
heard from, since a drive may fault on a COMMAND while DISABLED), then CONTROL disable. Once it
went out, a second ``safe_stop`` (or :meth:`close`) sends nothing until the next enable request.
"""

from __future__ import annotations

import logging
import math
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from fractions import Fraction
from typing import Final, NoReturn

import can

from dob_hil.config import DriveConfig
from dob_hil.errors import ConfigError, DriveFault, ProtocolError
from dob_hil.link import protocol
from dob_hil.link.base import EventHook, Feedback, FrameHook, LinkEvent, LinkEventKind
from dob_hil.link.closing import ClosingLink
from dob_hil.link.message import data_frame
from dob_hil.link.protocol import (
    DLC,
    MAX_PADDED_LEN,
    PROTOCOL_VERSION,
    ControlRequest,
    DriveState,
    FaultCode,
    FaultFrame,
    FrameKind,
    Status,
    frame_id,
)
from dob_hil.link.unwrap import CountUnwrapper

_log = logging.getLogger(__name__)

DEFAULT_STALE_WINDOW: Final = 32  # feedback up to this many sequence numbers behind is stale
MAX_READS_AFTER_DEADLINE: Final = 1024  # bounds the drain of already-queued frames after a timeout
MAX_CONSECUTIVE_RX_ERRORS: Final = 1000  # bus.recv raising this often in a row: the bus is broken
MAX_STOP_DRAIN: Final = 256  # frames safe_stop reads (non-blocking) to find the newest feedback
LEGACY_HEARTBEAT_BASE: Final = 0x700  # protocol version 1's HEARTBEAT id base (also CANopen NMT)
CLEAR_FAULT_HINT: Final = (
    "clear it with `dob-hil run --clear-fault` (or `clear_fault = true` in [drive]), "
    "which sends ClearFault before enabling"
)
N_AXES: Final = 1


_FEEDBACK_STRUCT: Final = struct.Struct("<iBB")  # the layout of protocol.FEEDBACK
_COMMAND_STRUCT: Final = struct.Struct("<hB")  # the layout of protocol.COMMAND
_FEEDBACK_DLC: Final = DLC[FrameKind.FEEDBACK]
_MAX_LEN: Final = MAX_PADDED_LEN
_STATUS_RESERVED: Final = protocol.STATUS_RESERVED_MASK
_ENABLED: Final = int(Status.ENABLED)
_FAULT: Final = int(Status.FAULT)
_SATURATED: Final = int(Status.SATURATED)
_ENABLED_SATURATED: Final = _ENABLED | _SATURATED
_STATE_ENABLED: Final = DriveState.ENABLED
_INF: Final = math.inf
_new_tuple: Final = tuple.__new__

_FAULT_INFO: Final = {
    FaultCode.WATCHDOG: "periods without a valid command",
    FaultCode.BAD_FRAME: "low byte of the offending id",
}


@dataclass(slots=True)
class LinkStats:
    """Counters of everything the link saw and did (cheap to keep; read them for the run report)."""

    rx_frames: int = 0
    feedback: int = 0  # valid feedback delivered
    missed_feedback: int = 0  # sequence numbers skipped between accepted feedback
    stale_feedback: int = 0
    malformed_frames: int = 0
    foreign_frames: int = 0
    error_frames: int = 0
    own_echoes: int = 0  # our own COMMAND/CONTROL frames received back (udp_multicast)
    rx_errors: int = 0  # bus.recv raised (a datagram or frame the interface could not decode)
    version_mismatches: int = 0  # heartbeats of another protocol version
    sequence_restarts: int = 0  # feedback sequence restarted when the drive entered ENABLED
    drive_faults: int = 0
    encoder_jumps: int = 0
    tx_frames: int = 0
    send_failures: int = 0
    clamped_commands: int = 0  # codes above the limit given to send_command, clamped
    nonfinite_currents: int = 0  # NaN/inf given to quantize, sent as 0 A


def describe_fault(fault: FaultFrame) -> str:
    """``WATCHDOG (info 10: periods without a valid command)``."""
    meaning = _FAULT_INFO.get(fault.code)
    return f"{fault.code.name} (info {fault.info}{': ' + meaning if meaning else ''})"


class DacQuantizer:
    """The drive's current quantizer and limit, as a pure function of a :class:`DriveConfig`.

    ``code = clamp(round_half_away(u / dac_lsb_A), -L, +L)``, ``L = floor(current_limit_A /
    dac_lsb_A)`` (exact), applied current ``code * dac_lsb_A``; a non-finite current gives code 0,
    0 A and ``saturated=True``. :class:`NativeDriveLink` delegates to it, and ``dob-hil replay``
    uses it to reproduce the link's commands bit for bit. Raises :class:`ConfigError` naming
    ``drive.dac_lsb_A`` or ``drive.current_limit_A`` for values the protocol cannot carry.
    """

    __slots__ = ("_limit_code", "_lsb_A", "_on_nonfinite", "_round_limit")

    def __init__(self, drive: DriveConfig, on_nonfinite: Callable[[float], None] | None = None) -> None:
        """``on_nonfinite(u)``: called with each non-finite current before it is replaced by 0 A."""
        if not drive.dac_lsb_A > 0.0 or not math.isfinite(drive.dac_lsb_A):
            raise ConfigError("drive.dac_lsb_A", f"must be a finite number > 0, got {drive.dac_lsb_A}")
        if not 0.0 < drive.current_limit_A < math.inf:
            raise ConfigError(
                "drive.current_limit_A", f"must be a finite number > 0, got {drive.current_limit_A}"
            )
        # exact floor(limit / lsb): the float quotient can round up (0.7 / 0.01 == 70.0), and then
        # limit_code * lsb would exceed the limit
        limit_code = math.floor(Fraction(drive.current_limit_A) / Fraction(drive.dac_lsb_A))
        if not 1 <= limit_code <= protocol.CURRENT_COUNTS_MAX:
            raise ConfigError(
                "drive.current_limit_A",
                f"{drive.current_limit_A} A is {limit_code} DAC LSBs of {drive.dac_lsb_A} A; "
                f"must be 1..{protocol.CURRENT_COUNTS_MAX}",
            )
        self._lsb_A = drive.dac_lsb_A
        self._limit_code = limit_code
        self._round_limit = limit_code + 0.5  # |u / lsb| at or above this rounds beyond the limit
        self._on_nonfinite = on_nonfinite

    @property
    def dac_lsb_A(self) -> float:
        return self._lsb_A

    @property
    def limit_code(self) -> int:
        """floor(current_limit_A / dac_lsb_A): the largest |DAC code| ever produced."""
        return self._limit_code

    @property
    def max_current_A(self) -> float:
        """The largest |current| ever applied: ``limit_code * dac_lsb_A``."""
        return self._limit_code * self._lsb_A

    def quantize(self, current_A: tuple[float, ...]) -> tuple[tuple[int, ...], tuple[float, ...], bool]:
        """((code,), (code * dac_lsb_A,), saturated) for the one axis of the native profile."""
        if len(current_A) != N_AXES:
            raise ProtocolError(f"current_A: the native profile drives 1 axis, got {len(current_A)} currents")
        u = current_A[0]
        if not -_INF < u < _INF:
            if self._on_nonfinite is not None:
                self._on_nonfinite(u)
            return (0,), (0.0,), True
        x = u / self._lsb_A
        if x >= self._round_limit:
            code = self._limit_code
            return (code,), (code * self._lsb_A,), True
        if x <= -self._round_limit:
            code = -self._limit_code
            return (code,), (code * self._lsb_A,), True
        # round_half_away(x), inline (the per-period path)
        if x >= 0.0:
            q = int(x)
            code = q + 1 if x - q >= 0.5 else q
        else:
            q = int(-x)
            code = -(q + 1) if -x - q >= 0.5 else -q
        return (code,), (code * self._lsb_A,), False


class NativeDriveLink(ClosingLink):
    """One drive of the native protocol on a python-can bus. See the module docstring."""

    n_axes: Final = N_AXES

    def __init__(
        self,
        bus: can.BusABC,
        drive: DriveConfig,
        *,
        frame_hook: FrameHook | None = None,
        event_hook: EventHook | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        owns_bus: bool = False,
        stale_window: int = DEFAULT_STALE_WINDOW,
        max_counts_step: int | None = None,
        send_timeout_ns: int | None = None,
    ) -> None:
        """
        ``owns_bus``: :meth:`close` shuts the bus down. ``stale_window``: feedback whose sequence
        number is 0..``stale_window`` behind the last accepted one is discarded as stale; anything
        further ahead is accepted (a gap counts in ``stats.missed_feedback``). ``max_counts_step``:
        an unwrapped step larger than this raises an ENCODER_JUMP event (the feedback is still
        delivered); default a quarter of the counter range, ``2**(encoder_bits - 2)``.
        ``send_timeout_ns``: passed to ``bus.send`` (None: the interface's default).
        """
        if drive.profile != "native":
            raise ConfigError(
                "drive.profile", f"NativeDriveLink drives the native profile, got {drive.profile!r}"
            )
        quantizer = DacQuantizer(drive, on_nonfinite=self._nonfinite_current)
        self._clear_fault_first = drive.clear_fault
        if not drive.encoder_counts_per_unit > 0.0:
            raise ConfigError(
                "drive.encoder_counts_per_unit", f"must be > 0, got {drive.encoder_counts_per_unit}"
            )
        if not 1 <= stale_window <= 127:
            raise ConfigError("stale_window", f"must be 1..127, got {stale_window}")
        node = drive.node_id
        try:
            self._feedback_id = frame_id(FrameKind.FEEDBACK, node)
        except ProtocolError as exc:
            raise ConfigError("drive.node_id", str(exc).removeprefix("node_id: ")) from None
        self._fault_id = frame_id(FrameKind.FAULT, node)
        self._heartbeat_id = frame_id(FrameKind.HEARTBEAT, node)
        self._command_id = frame_id(FrameKind.COMMAND, node)
        self._control_id = frame_id(FrameKind.CONTROL, node)
        self._own_tx_ids = frozenset((self._command_id, self._control_id))
        self._handlers: dict[int, Callable[[can.Message, int], Feedback | None]] = {
            self._feedback_id: self._on_feedback,
            self._fault_id: self._on_fault,
            self._heartbeat_id: self._on_heartbeat,
        }

        self._bus = bus
        self._drive = drive
        self._node = node
        self._frame_hook = frame_hook
        self._event_hook = event_hook
        self._clock_ns = clock_ns
        self._owns_bus = owns_bus
        self._send_timeout_s = None if send_timeout_ns is None else send_timeout_ns * 1e-9

        self._quantizer = quantizer
        self._quantize = quantizer.quantize
        self.quantize = quantizer.quantize  # type: ignore[method-assign]  # (see quantize)
        self._lsb_A = quantizer.dac_lsb_A
        self._limit_code = quantizer.limit_code
        self._counts_per_unit = drive.encoder_counts_per_unit
        self._unwrapper = CountUnwrapper(drive.encoder_bits)
        self._max_counts_step = 2 ** (drive.encoder_bits - 2) if max_counts_step is None else max_counts_step
        self._stale_from = 256 - stale_window  # (seq - last) mod 256 >= this: stale

        self._last_seq: int | None = None
        self._state: DriveState | None = None
        self._last_fault: FaultFrame | None = None
        self._enable_mask = 0  # 0x80 while the host wants the drive enabled (COMMAND bit 7)
        self._enable_attempt_faults = -1  # stats.drive_faults when the enable attempt began; -1: none
        self._enable_seen = False
        self._refusal: str | None = None  # why the drive refuses the current enable attempt
        self._resync = False  # a heartbeat reported entering ENABLED: the next feedback may restart
        self._peer_version: int | None = None  # a protocol version the drive reported, not ours
        self._legacy_heartbeats = 0  # frames that look like a version-1 heartbeat of our node
        self._first_rejection: str | None = None  # what the first malformed frame was
        self._stopped = False  # a complete stop sequence went out and no enable since
        self._rx_errors_in_row = 0
        self._closed = False
        # a valid feedback read while polling for enable is kept for the next receive_feedback()
        self._pending_feedback: Feedback | None = None
        self.stats = LinkStats()

    # --- properties ------------------------------------------------------------------------------
    @property
    def current_limit_A(self) -> float:
        """The configured current limit; the largest current actually sent is :attr:`max_current_A`."""
        return self._drive.current_limit_A

    @property
    def max_current_A(self) -> float:
        return self._limit_code * self._lsb_A

    @property
    def limit_code(self) -> int:
        """floor(current_limit_A / dac_lsb_A): the largest |DAC code| ever sent."""
        return self._limit_code

    @property
    def dac_lsb_A(self) -> float:
        return self._lsb_A

    @property
    def node_id(self) -> int:
        return self._node

    @property
    def drive_state(self) -> DriveState | None:
        """The last state the drive reported (heartbeat, feedback status or a FAULT frame)."""
        return self._state

    @property
    def faulted(self) -> bool:
        return self._state is DriveState.FAULT

    @property
    def last_fault(self) -> FaultFrame | None:
        """The last FAULT frame received (kept after the fault is cleared)."""
        return self._last_fault

    @property
    def fault_description(self) -> str | None:
        """The last fault for an error message (with what to widen for a watchdog trip), or None."""
        if self._last_fault is None:
            return None
        text = describe_fault(self._last_fault)
        if self._last_fault.code is FaultCode.WATCHDOG:
            text += (
                "; the drive missed this host's commands: on a busy machine widen its watchdog "
                "(drive.watchdog_periods; python -m firmware_sim --watchdog-periods) and the host "
                "timeout (--feedback-timeout-periods) together"
            )
        return text

    @property
    def last_seq(self) -> int | None:
        """Sequence number of the last accepted feedback."""
        return self._last_seq

    @property
    def enable_requested(self) -> bool:
        return self._enable_mask != 0

    @property
    def closed(self) -> bool:
        return self._closed

    # --- receiving -------------------------------------------------------------------------------
    def receive_feedback(self, timeout_ns: int) -> Feedback | None:
        """The next valid feedback of our drive, or None once ``timeout_ns`` (wall clock) has passed."""
        if self._closed:
            self._check_open()
        if self._pending_feedback is not None:
            pending, self._pending_feedback = self._pending_feedback, None
            return pending
        recv = self._bus.recv
        clock_ns = self._clock_ns
        hook = self._frame_hook
        feedback_id = self._feedback_id
        if timeout_ns > 0:
            deadline_ns = time.monotonic_ns() + timeout_ns
            timeout_s = timeout_ns * 1e-9
        else:  # lockstep: read what is queued, no clock needed
            deadline_ns, timeout_s = 0, 0.0
        reads_after_deadline = 0
        while True:
            try:  # (inlined rather than self._recv: this is the per-period path)
                msg = recv(timeout_s)
            except can.CanError as exc:
                self._rx_error(exc)  # an event; raises once the bus is clearly broken
                if deadline_ns:
                    remaining_ns = deadline_ns - time.monotonic_ns()
                    if remaining_ns <= 0:
                        return None
                    timeout_s = remaining_ns * 1e-9
                continue
            if msg is None:
                return None
            if self._rx_errors_in_row:
                self._rx_errors_in_row = 0
            now_ns = clock_ns()
            if hook is not None:
                hook(msg, True)
            self.stats.rx_frames += 1
            if msg.arbitration_id == feedback_id and not (
                msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame or msg.is_fd
            ):
                data = msg.data
                if len(data) == _FEEDBACK_DLC:
                    # _on_feedback's common case, inline (the per-period path): the next sequence
                    # number of an ENABLED drive, status ENABLED (and SATURATED) only, no enable
                    # attempt under way, a plausible encoder step; the same effects and result
                    raw_counts, seq, status = _FEEDBACK_STRUCT.unpack(data)
                    last_seq = self._last_seq
                    unwrap = self._unwrapper
                    last = unwrap._last
                    if (
                        status | _SATURATED == _ENABLED_SATURATED  # ENABLED, maybe SATURATED, no other bit
                        and last_seq is not None
                        and (seq - last_seq) & 0xFF == 1
                        and last is not None
                        and self._state is _STATE_ENABLED
                        and not self._resync
                        and self._enable_attempt_faults < 0
                    ):
                        half = unwrap._half
                        step = ((raw_counts - last + half) & unwrap._mask) - half  # update_step
                        max_step = self._max_counts_step
                        if -max_step <= step <= max_step:
                            self._last_seq = seq
                            unwrap._last = raw_counts
                            unwrap._position = counts = unwrap._position + step
                            self.stats.feedback += 1
                            return _new_tuple(
                                Feedback,
                                (
                                    now_ns,
                                    seq,
                                    (raw_counts,),
                                    (counts,),
                                    (counts / self._counts_per_unit,),
                                    True,
                                    False,
                                    status != _ENABLED,
                                ),
                            )
                feedback = self._on_feedback(msg, now_ns)
            else:
                feedback = self._dispatch(msg, now_ns)
            if feedback is not None:
                return feedback
            remaining_ns = deadline_ns - time.monotonic_ns() if deadline_ns else 0
            if remaining_ns > 0:
                timeout_s = remaining_ns * 1e-9
            else:
                timeout_s = 0.0
                reads_after_deadline += 1
                if reads_after_deadline > MAX_READS_AFTER_DEADLINE:
                    return None

    def _recv(
        self, recv: Callable[[float | None], can.Message | None], timeout_s: float
    ) -> can.Message | None:
        """One frame, or None on timeout; a frame the bus could not deliver is an event, not an end."""
        while True:
            try:
                msg = recv(timeout_s)
            except can.CanError as exc:
                self._rx_error(exc)
                continue
            self._rx_errors_in_row = 0
            return msg

    def _rx_error(self, exc: can.CanError) -> None:
        """``bus.recv`` raised: report it and read on; :data:`MAX_CONSECUTIVE_RX_ERRORS` in a row end it."""
        self.stats.rx_errors += 1
        self._rx_errors_in_row += 1
        cause = exc.__cause__
        detail = f"{exc}" + (f" ({type(cause).__name__}: {cause})" if cause is not None else "")
        self._event(
            self._clock_ns(),
            LinkEventKind.MALFORMED_FRAME,
            f"node {self._node}: the bus could not deliver a received frame, skipped: {detail}",
        )
        if self._rx_errors_in_row >= MAX_CONSECUTIVE_RX_ERRORS:
            raise DriveFault(
                f"node {self._node}: receiving from the CAN bus failed {self._rx_errors_in_row} times "
                f"in a row: {detail}"
            ) from exc

    def _dispatch(self, msg: can.Message, now_ns: int) -> Feedback | None:
        """Any received frame: validate, update the link state, report; a Feedback if it is one."""
        if msg.is_error_frame:
            self.stats.error_frames += 1
            self._event(now_ns, LinkEventKind.ERROR_FRAME, f"CAN error frame {_describe(msg)}")
            return None
        if msg.is_extended_id or msg.is_remote_frame:
            self.stats.foreign_frames += 1
            what = "29-bit id" if msg.is_extended_id else "remote frame"
            self._event(now_ns, LinkEventKind.FOREIGN_FRAME, f"{what} {_describe(msg)} skipped")
            return None
        aid = msg.arbitration_id
        handler = self._handlers.get(aid)
        if handler is None:
            if aid in self._own_tx_ids:
                self.stats.own_echoes += 1
                return None
            if aid == LEGACY_HEARTBEAT_BASE + self._node and len(msg.data) == 1 and msg.data[0] <= 2:
                self._legacy_heartbeats += 1
            self.stats.foreign_frames += 1
            self._event(
                now_ns, LinkEventKind.FOREIGN_FRAME, f"{_describe(msg)} is no frame of node {self._node}"
            )
            return None
        if msg.is_fd:
            self._malformed(now_ns, msg, "a CAN FD frame; the native protocol is classic CAN")
            return None
        return handler(msg, now_ns)

    def _on_feedback(self, msg: can.Message, now_ns: int) -> Feedback | None:
        data = msg.data
        n = len(data)
        if n < _FEEDBACK_DLC or n > _MAX_LEN or data[5] & _STATUS_RESERVED:
            try:  # the codec names what is wrong
                protocol.decode_feedback(data)
                problem = "does not decode"
            except ProtocolError as exc:
                problem = str(exc)
            self._malformed(now_ns, msg, problem)
            return None
        raw_counts, seq, status = _FEEDBACK_STRUCT.unpack_from(data)
        last_seq = self._last_seq
        if (
            status & _ENABLED
            and not status & _FAULT
            and (self._resync or self._state is not DriveState.ENABLED)
        ):
            if last_seq is not None and (seq - last_seq) & 0xFF != 1:
                self.stats.sequence_restarts += 1
            last_seq = None  # entering ENABLED: the drive may restart its sequence (PROTOCOL.md)
            self._resync = False
        if last_seq is not None:
            ahead = (seq - last_seq) & 0xFF
            if ahead == 0 or ahead >= self._stale_from:
                self.stats.stale_feedback += 1
                self._event(
                    now_ns,
                    LinkEventKind.STALE_FEEDBACK,
                    f"node {self._node}: feedback seq {seq} after {last_seq} "
                    f"({'duplicate' if ahead == 0 else f'{256 - ahead} behind'}), discarded",
                )
                return None
            if ahead > 1:
                self.stats.missed_feedback += ahead - 1
        self._last_seq = seq
        counts, step = self._unwrapper.update_step(raw_counts)
        if step is not None and (step > self._max_counts_step or step < -self._max_counts_step):
            self.stats.encoder_jumps += 1
            self._event(
                now_ns,
                LinkEventKind.ENCODER_JUMP,
                f"node {self._node}: encoder step {step} counts at seq {seq} "
                f"exceeds the plausibility bound {self._max_counts_step}",
            )
        enabled = status & _ENABLED != 0
        fault = status & _FAULT != 0
        state = DriveState.FAULT if fault else DriveState.ENABLED if enabled else DriveState.DISABLED
        if state is not self._state:
            self._change_state(now_ns, state, "feedback status")
        elif self._enable_attempt_faults >= 0:
            self._attempt_report(state)
        self.stats.feedback += 1
        # tuple.__new__ directly: Feedback(...) without NamedTuple's Python-level __new__
        return _new_tuple(
            Feedback,
            (
                now_ns,
                seq,
                (raw_counts,),
                (counts,),
                (counts / self._counts_per_unit,),
                enabled,
                fault,
                status & _SATURATED != 0,
            ),
        )

    def _on_fault(self, msg: can.Message, now_ns: int) -> None:
        try:
            fault = protocol.decode_fault(msg.data)
        except ProtocolError as exc:
            self._malformed(now_ns, msg, str(exc))
            return None
        repeat = self._state is DriveState.FAULT and fault == self._last_fault
        self._last_fault = fault
        if repeat:  # the drive repeats its FAULT frame while in FAULT: no new fault, no new event
            return None
        self._state = DriveState.FAULT
        self._enable_seen = False
        self._stopped = False  # the drive changed state on its own: a later stop is sent again
        self.stats.drive_faults += 1
        self._event(
            now_ns, LinkEventKind.DRIVE_FAULT, f"node {self._node}: drive fault {describe_fault(fault)}"
        )
        return None

    def _on_heartbeat(self, msg: can.Message, now_ns: int) -> None:
        try:
            heartbeat = protocol.decode_heartbeat(msg.data)
        except ProtocolError as exc:
            self._malformed(now_ns, msg, str(exc))
            return None
        if heartbeat.version != PROTOCOL_VERSION:
            self.stats.version_mismatches += 1
            self._peer_version = heartbeat.version
            if self._enable_attempt_faults >= 0:
                self._refusal = self._version_text()
            self._malformed(now_ns, msg, self._version_text())
            return None
        state = heartbeat.state
        if state is DriveState.ENABLED and self._state is not DriveState.ENABLED:
            self._resync = True
        if state is not self._state:
            self._change_state(now_ns, state, "heartbeat")
        elif self._enable_attempt_faults >= 0:
            self._attempt_report(state)
        return None

    def _change_state(self, now_ns: int, state: DriveState, source: str) -> None:
        old = "unknown" if self._state is None else self._state.name
        self._state = state
        if self._enable_attempt_faults >= 0:
            self._attempt_report(state)
        self._event(now_ns, LinkEventKind.DRIVE_STATE, f"node {self._node}: {old} -> {state.name} ({source})")

    def _attempt_report(self, state: DriveState) -> None:
        """A state the drive reported during an enable attempt."""
        self._enable_seen = state is DriveState.ENABLED
        if state is DriveState.FAULT:  # a drive in FAULT refuses to enable until ClearFault
            self._refusal = f"the drive is in FAULT ({self._fault_text()})"

    def _version_text(self) -> str:
        return (
            f"the drive speaks native protocol version {self._peer_version}, "
            f"this host version {PROTOCOL_VERSION}"
        )

    def _fault_text(self) -> str:
        if self._last_fault is None:
            return "fault code unknown: its FAULT frame was sent before this host listened"
        return f"last fault {describe_fault(self._last_fault)}"

    def _malformed(self, now_ns: int, msg: can.Message, problem: str) -> None:
        self.stats.malformed_frames += 1
        if self._first_rejection is None:
            self._first_rejection = f"{_describe(msg)}: {problem}"
        self._event(now_ns, LinkEventKind.MALFORMED_FRAME, f"{_describe(msg)} skipped: {problem}")

    def _event(self, time_ns: int, kind: LinkEventKind, message: str) -> None:
        if self._event_hook is not None:
            self._event_hook(LinkEvent(time_ns, kind, message))

    # --- quantizing and sending --------------------------------------------------------------------
    def quantize(self, current_A: tuple[float, ...]) -> tuple[tuple[int, ...], tuple[float, ...], bool]:
        """((code,), (code * dac_lsb_A,), saturated): :meth:`DacQuantizer.quantize`, plus an
        INVALID_COMMAND event (and ``stats.nonfinite_currents``) for a non-finite current.

        (An instance's ``quantize`` is its quantizer's own method, bound in ``__init__``, which
        reports a non-finite current to :meth:`_nonfinite_current`: one call per period.)"""
        return self._quantize(current_A)

    def _nonfinite_current(self, u: float) -> None:
        self.stats.nonfinite_currents += 1
        self._event(
            self._clock_ns(),
            LinkEventKind.INVALID_COMMAND,
            f"node {self._node}: non-finite current {u!r} A requested; 0 A commanded instead",
        )

    def send_command(self, codes: tuple[int, ...], answers_seq: int) -> int:
        """Send one COMMAND answering feedback ``answers_seq`` (taken mod 128); returns clock_ns()
        read as soon as the bus took the frame (the frame hook runs after it).

        The code is clamped to +-:attr:`limit_code` as the last step before packing (quantize
        already does that; a clamp here is counted in ``stats.clamped_commands``). The enable bit
        is set between :meth:`request_enable` and :meth:`safe_stop`/:meth:`disable`.
        Raises :class:`~dob_hil.errors.DriveFault` when ``bus.send`` fails.
        """
        if len(codes) != N_AXES:
            raise ProtocolError(
                f"COMMAND.current_counts: the native profile drives 1 axis, got {len(codes)} codes"
            )
        code = codes[0]
        limit = self._limit_code  # saturate_current_counts, inline (the per-period path)
        if code > limit:
            limited = limit
        elif code < -limit:
            limited = -limit
        else:
            limited = code
        if limited != code:
            self.stats.clamped_commands += 1
        try:
            payload = _COMMAND_STRUCT.pack(limited, (answers_seq & 0x7F) | self._enable_mask)
        except (struct.error, TypeError):
            raise ProtocolError(
                f"COMMAND: expected integer current_counts and answers_seq, got {code!r} and {answers_seq!r}"
            ) from None
        # _send, inline, with the send time read as soon as the bus took the frame: the frame hook
        # (logging) comes after, outside the feedback-to-command path
        if self._closed:
            self._check_open()
        msg = data_frame(0.0, self._command_id, payload)
        try:
            self._bus.send(msg, self._send_timeout_s)
        except can.CanError as exc:
            self._send_failed(exc, self._command_id, "COMMAND")
        sent_ns = self._clock_ns()
        self.stats.tx_frames += 1
        if self._frame_hook is not None:
            self._frame_hook(msg, False)
        return sent_ns

    def _send_failed(self, exc: can.CanError, arbitration_id: int, what: str) -> NoReturn:
        self.stats.send_failures += 1
        text = f"node {self._node}: sending {what} (id 0x{arbitration_id:03X}) failed: {exc}"
        self._event(self._clock_ns(), LinkEventKind.SEND_FAILED, text)
        raise DriveFault(text) from exc

    def _send(self, arbitration_id: int, payload: bytes, what: str) -> None:
        if self._closed:
            self._check_open()
        # no timestamp: the interface stamps what it sends (the frame hook falls back to the
        # loop's clock where it does not)
        msg = can.Message(arbitration_id=arbitration_id, is_extended_id=False, data=payload)
        try:
            self._bus.send(msg, self._send_timeout_s)
        except can.CanError as exc:
            self._send_failed(exc, arbitration_id, what)
        self.stats.tx_frames += 1
        if self._frame_hook is not None:
            self._frame_hook(msg, False)

    def _send_control(self, request: ControlRequest) -> None:
        self._send(
            self._control_id,
            protocol.encode_control(protocol.ControlFrame(request)),
            f"CONTROL {request.name}",
        )

    # --- enable, disable, stop -----------------------------------------------------------------------
    def request_enable(self) -> None:
        """Send CONTROL enable and start an enable attempt; commands carry the enable bit from now on."""
        self._enable_attempt_faults = self.stats.drive_faults
        self._enable_seen = False
        self._refusal = self._version_text() if self._peer_version is not None else None
        self._enable_mask = 0x80
        self._stopped = False
        self._send_control(ControlRequest.ENABLE)

    def poll_enabled(self) -> bool:
        """Read every frame already queued; True once the drive reported enabled since the request.

        Raises :class:`~dob_hil.errors.DriveFault` if no attempt was requested, or the drive
        reported a fault during the attempt.
        """
        self._check_attempt()
        while True:
            msg = self._recv(self._bus.recv, 0.0)
            if msg is None:
                return self._attempt_result()
            self._consume(msg)
            self._check_attempt()

    def wait_enabled(self, timeout_ns: int) -> None:
        """Block until the drive reports enabled since :meth:`request_enable`; DriveFault if not."""
        self._check_attempt()
        deadline_ns = time.monotonic_ns() + timeout_ns
        while True:
            remaining_ns = deadline_ns - time.monotonic_ns()
            msg = self._recv(self._bus.recv, max(remaining_ns, 0) * 1e-9)
            if msg is None:
                break
            self._consume(msg)
            self._check_attempt()
            if self._enable_seen and self.poll_enabled():  # still so once every queued frame is read
                return
        if self.poll_enabled():  # frames that were queued when the deadline passed
            return
        raise self._not_enabled(timeout_ns)

    def _not_enabled(self, timeout_ns: int) -> DriveFault:
        self._enable_mask = 0
        self._enable_attempt_faults = -1
        state = "nothing" if self._state is None else self._state.name
        fault = ""
        if self._state is DriveState.FAULT or self._last_fault is not None:
            fault = f"; {self._fault_text()}"
        text = (
            f"node {self._node}: the drive did not report enabled within {timeout_ns / 1e6:g} ms "
            f"(last reported state: {state}{fault}){self._diagnosis()}"
        )
        if self._state is DriveState.FAULT:
            text += f"; {CLEAR_FAULT_HINT}"
        elif self._state is None:
            text += "; check the bus (interface, channel, bitrate, udp_multicast port) and drive.node_id"
        return DriveFault(text)

    def _diagnosis(self, *, version: bool = True) -> str:
        """What the link rejected of our node so far, for an enable failure."""
        s = self.stats
        parts = []
        rejected = s.malformed_frames + s.stale_feedback
        if rejected or s.rx_errors:
            first = f"; first: {self._first_rejection}" if self._first_rejection else ""
            parts.append(
                f"; rejected {rejected} frame(s) of node {self._node} ({s.malformed_frames} malformed, "
                f"{s.stale_feedback} stale, {s.rx_errors} undeliverable{first})"
            )
        if version and self._peer_version is not None:
            parts.append(f"; {self._version_text()}")
        if self._legacy_heartbeats:
            parts.append(
                f"; heard {self._legacy_heartbeats} frame(s) at 0x{LEGACY_HEARTBEAT_BASE + self._node:03X} "
                "that look like a native protocol version 1 heartbeat (or a CANopen node's)"
            )
        return "".join(parts)

    def enable(self, timeout_ns: int, retry_interval_ns: int = 100_000_000) -> None:
        """request_enable() then wait_enabled(): for a drive serviced by its own clock.

        The CONTROL enable is repeated every ``retry_interval_ns`` until the drive reports enabled
        or ``timeout_ns`` passes: a CAN frame can be lost, and a drive (or a simulated drive
        process) that comes up after the request never saw it. A fault reported meanwhile ends
        the attempt at once with :class:`~dob_hil.errors.DriveFault`.
        """
        if self._clear_fault_first:
            self.clear_fault(timeout_ns)
        deadline_ns = time.monotonic_ns() + timeout_ns
        faults_before = self.stats.drive_faults
        while True:
            self.request_enable()
            remaining_ns = deadline_ns - time.monotonic_ns()
            try:
                self.wait_enabled(max(0, min(retry_interval_ns, remaining_ns)))
                return
            except DriveFault:
                if self.stats.drive_faults > faults_before or self._refusal is not None:
                    raise
                if time.monotonic_ns() >= deadline_ns:
                    raise self._not_enabled(timeout_ns) from None

    def enable_lockstep(self, service: Callable[[], int], max_rounds: int = 3) -> None:
        """Enable against a drive serviced in this thread (the embedded lockstep drive):
        ``service()`` lets the drive act on the request between polls; DriveFault if it does not.
        With ``drive.clear_fault`` a ClearFault goes first."""
        if self._clear_fault_first:
            self.request_clear_fault()
            service()
        self.request_enable()
        for _ in range(max_rounds):
            service()
            if self.poll_enabled():
                return
        raise DriveFault(f"node {self._node}: the simulated drive did not report enabled")

    def request_clear_fault(self) -> None:
        """Send CONTROL clear-fault; the drive answers with a HEARTBEAT of its new state."""
        self._send_control(ControlRequest.CLEAR_FAULT)

    def clear_fault(self, timeout_ns: int, retry_interval_ns: int = 100_000_000) -> None:
        """Send ClearFault (repeated every ``retry_interval_ns``) until the drive reports a state
        other than FAULT; :class:`~dob_hil.errors.DriveFault` naming the fault if it does not.

        A drive that is not in FAULT answers with its state, so this is harmless before any enable.
        """
        deadline_ns = time.monotonic_ns() + timeout_ns
        while True:
            self._state = None  # only a report sent after the request counts
            self.request_clear_fault()
            retry_ns = time.monotonic_ns() + min(retry_interval_ns, max(0, deadline_ns - time.monotonic_ns()))
            while True:
                remaining_ns = retry_ns - time.monotonic_ns()
                msg = self._recv(self._bus.recv, max(remaining_ns, 0) * 1e-9)
                if msg is not None:
                    self._consume(msg)
                if self._out_of_fault():
                    return
                if msg is None or time.monotonic_ns() >= retry_ns:
                    break
            if time.monotonic_ns() >= deadline_ns:
                state = "nothing" if self._state is None else self._state.name
                raise DriveFault(
                    f"node {self._node}: the drive did not leave FAULT within {timeout_ns / 1e6:g} ms of "
                    f"ClearFault (last reported state: {state}; {self._fault_text()}){self._diagnosis()}"
                )

    def _out_of_fault(self) -> bool:
        return self._state is not None and self._state is not DriveState.FAULT

    def disable(self) -> None:
        """The stop sequence (see :meth:`safe_stop`), raising DriveFault when a frame cannot be sent."""
        self._stop_sequence(raise_errors=True)

    def safe_stop(self) -> None:
        """The stop sequence, once. Never raises.

        Reads the frames already queued (non-blocking) so that the newest feedback is known; if
        the drive was last reported ENABLED (or FAULT: a report that may be corrupt, and a faulted
        drive ignores it), sends a zero-current COMMAND with the enable bit clear answering that
        feedback; then CONTROL disable. Each frame is attempted even if the
        other fails; failures are reported to ``event_hook`` (and the Python log if even that
        fails), and a stop with a failed frame is tried again by the next call. A stop that went
        out is not repeated until the next :meth:`request_enable`. After :meth:`close` it does
        nothing.
        """
        if self._closed or self._stopped:
            return
        self._stop_sequence(raise_errors=False)

    def _stop_sequence(self, *, raise_errors: bool) -> None:
        self._enable_mask = 0
        self._enable_attempt_faults = -1
        self._stop_step("reading queued frames", self._drain_queued, raise_errors)
        ok = True
        if self._state is DriveState.ENABLED or self._state is DriveState.FAULT:
            seq = 0 if self._last_seq is None else self._last_seq
            payload = _COMMAND_STRUCT.pack(0, seq & 0x7F)
            ok = self._stop_step(
                "COMMAND (stop)",
                lambda: self._send(self._command_id, payload, "COMMAND (stop)"),
                raise_errors,
            )
        ok = (
            self._stop_step(
                "CONTROL DISABLE", lambda: self._send_control(ControlRequest.DISABLE), raise_errors
            )
            and ok
        )
        self._stopped = ok

    def _drain_queued(self) -> None:
        """Read up to :data:`MAX_STOP_DRAIN` frames already queued (the newest feedback last)."""
        for _ in range(MAX_STOP_DRAIN):
            msg = self._recv(self._bus.recv, 0.0)
            if msg is None:
                return
            self._consume(msg)
        self._pending_feedback = None

    # --- helpers -----------------------------------------------------------------------------------
    def _consume(self, msg: can.Message) -> None:
        now_ns = self._clock_ns()
        if self._frame_hook is not None:
            self._frame_hook(msg, True)
        self.stats.rx_frames += 1
        feedback = self._dispatch(msg, now_ns)
        if feedback is not None:
            self._pending_feedback = feedback  # the newest; an older pending one is superseded

    def _check_attempt(self) -> None:
        if self._enable_attempt_faults < 0:
            raise DriveFault(f"node {self._node}: no enable attempt in progress; call request_enable() first")
        if self.stats.drive_faults > self._enable_attempt_faults:
            self._enable_mask = 0
            self._enable_attempt_faults = -1
            fault = "?" if self._last_fault is None else describe_fault(self._last_fault)
            raise DriveFault(
                f"node {self._node}: the drive faulted while enabling: {fault}{self._diagnosis()}; "
                f"{CLEAR_FAULT_HINT}"
            )
        if self._refusal is not None and not self._enable_seen:
            refusal, self._refusal = self._refusal, None
            self._enable_mask = 0
            self._enable_attempt_faults = -1
            hint = "" if self._peer_version is not None else f"; {CLEAR_FAULT_HINT}"
            diagnosis = self._diagnosis(version=False)
            raise DriveFault(f"node {self._node}: the drive refuses to enable: {refusal}{diagnosis}{hint}")

    def _attempt_result(self) -> bool:
        if self._enable_seen:
            self._enable_attempt_faults = -1
            return True
        return False


def round_half_away(x: float) -> int:
    """Round to the nearest integer, ties away from zero (C ``lround``); exact for every double."""
    if x >= 0.0:
        q = int(x)
        return q + 1 if x - q >= 0.5 else q
    q = int(-x)
    return -(q + 1) if -x - q >= 0.5 else -q


def _describe(msg: can.Message) -> str:
    if msg.is_error_frame:
        return f"(error class 0x{msg.arbitration_id:X}, data {bytes(msg.data).hex() or '-'})"
    width = 8 if msg.is_extended_id else 3
    return f"id 0x{msg.arbitration_id:0{width}X} DLC {msg.dlc} data {bytes(msg.data).hex() or '-'}"


__all__ = [
    "DEFAULT_STALE_WINDOW",
    "DacQuantizer",
    "LinkStats",
    "NativeDriveLink",
    "describe_fault",
    "round_half_away",
]
