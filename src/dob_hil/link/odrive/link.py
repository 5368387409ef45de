"""The ODrive profile's :class:`~dob_hil.link.base.DriveLink`: CANSimple over a python-can bus.

One axis (``drive.node_id``, 0..63). The frames are those of :mod:`dob_hil.link.odrive.codec`.

Clock and sequence numbers. The drive sends Get_Encoder_Estimates every ``encoder_msg_rate_ms``
(= the control period), so the drive is the clock, as with the native profile. CANSimple frames
carry no sequence number; the link derives one from arrival times: the first estimate gets 0
and each later one ``previous + max(1, round(gap / period))`` (mod 256), where ``gap`` is the
time between the two frames' bus timestamps (``time.time()`` at receipt where the interface gives
none). A frame lost on the bus shows as a gap of two periods, so the real-time runner fills it
like a lost native feedback; frames read together after a stall of this process keep their bus
timestamps and are spaced correctly. In lockstep (no wall clock, after :meth:`enable_lockstep`)
every estimate is one more, and the stamps are the simulated drive's. An estimate stamped before
the last one (reordered) or a repeat of the last one (same stamp and payload) is STALE_FEEDBACK
and discarded. With ``encoder_msg_rate_ms = 0`` (host-clocked) :meth:`send_sync` (alias
``send_trigger``) sends the RTR Get_Encoder_Estimates that triggers each sample, and the answer
gets the trigger's index as sequence number.

Receiving. Estimates are checked (DLC 8, both floats finite, the position within an int32
count: anything else is a MALFORMED_FRAME event and never reaches the controller) and quantized
to the encoder (``counts = round(pos_turns * encoder_cpr)``, ``position = counts /
encoder_counts_per_unit``; the float as sent stays in the frame log). Heartbeats give
DRIVE_STATE events; after enabling, a heartbeat with axis errors or out of CLOSED_LOOP_CONTROL
ends the run: :meth:`receive_feedback` raises
:class:`~dob_hil.errors.DriveFault` naming the state and the error bits. Other nodes' frames,
unknown commands, 29-bit ids and error frames are events and skipped; our own command frames and
RTR echoed back (udp_multicast) are counted and skipped.

Commanding. ``quantize`` clamps the current at ``current_limit_A``, converts it to N m with the
torque constant and rounds to float32 (the wire's type), stepping one float32 ulp towards zero
if rounding went past the limit. The command "code" is the float32's bit pattern as an int32:
exact, and what the log's ``dac_counts`` field records. Enabling: Clear_Errors (if asked),
Set_Controller_Mode (TORQUE_CONTROL, PASSTHROUGH), Set_Axis_State CLOSED_LOOP_CONTROL, then wait
for a heartbeat showing it. Safe stop: Set_Input_Torque 0, then Set_Axis_State IDLE.

Per-period fast paths (``FAST_PATH``, :attr:`OdriveDriveLink.fast`; the same results as the
general path, tests/odrive/test_fast_path.py): in lockstep with RTR triggers the answer to the
outstanding trigger is judged in one call (anything unusual, a first, stale, malformed or
unasked-for estimate, goes through the general checks); ``quantize`` rounds a current within the
limit to float32 with ``struct`` (the same C cast as numpy's) and keeps the bytes, so that
``send_command`` given those very codes sends them without converting back; a current beyond the
limit gets the limit's command computed once; the lockstep RTR is one ``Message`` sent every
period (it has no data, and nothing on the lockstep path changes a frame once sent).
"""

from __future__ import annotations

import logging
import math
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

import can
import numpy as np

from dob_hil.config import DriveConfig
from dob_hil.errors import ConfigError, DriveFault, ProtocolError
from dob_hil.link.base import EventHook, Feedback, FrameHook, LinkEvent, LinkEventKind
from dob_hil.link.closing import ClosingLink
from dob_hil.link.message import data_frame
from dob_hil.link.odrive import codec
from dob_hil.link.odrive.codec import AxisState, CmdId, ControlMode, InputMode
from dob_hil.link.odrive.options import OdriveOptions

_log = logging.getLogger(__name__)

N_AXES: Final = 1
SEQ_MODULO: Final = 256
MAX_READS_AFTER_DEADLINE: Final = 1024
MAX_COUNTS: Final = 2**31 - 1  # estimates beyond an int32 count are implausible (malformed)
_ESTIMATES: Final = struct.Struct("<ff")
_HEARTBEAT: Final = struct.Struct("<IBBBx")
_TORQUE: Final = struct.Struct("<f4x")
_BITS: Final = struct.Struct("<i")
_F32: Final = struct.Struct("<f")
_F32_AND_BITS: Final = struct.Struct("<fi")  # 4 bytes twice: as a float32, as an int32
_DLC: Final = codec.DLC
_INF: Final = math.inf  # (a module constant: one load on the per-period path)
_CLOSED_LOOP: Final = int(AxisState.CLOSED_LOOP_CONTROL)
_PAD4: Final = bytes(4)  # Set_Input_Torque's bytes 4..7
FAST_PATH = True  # False: every frame and command through the general path (the fast path's tests)


@dataclass(slots=True)
class OdriveLinkStats:
    rx_frames: int = 0
    feedback: int = 0
    missed_feedback: int = 0  # sequence numbers skipped (gaps in arrival times)
    stale_feedback: int = 0  # duplicates and estimates stamped before the last ones
    malformed_frames: int = 0
    nonfinite_estimates: int = 0
    foreign_frames: int = 0
    error_frames: int = 0
    own_echoes: int = 0
    heartbeats: int = 0
    axis_errors: int = 0  # heartbeats reporting axis errors
    tx_frames: int = 0
    send_failures: int = 0
    clamped_commands: int = 0
    nonfinite_currents: int = 0


def describe_heartbeat(hb: codec.Heartbeat) -> str:
    return f"{hb.axis_state.name}, axis error 0x{hb.axis_error:08X} ({codec.error_names(hb.axis_error)})"


class TorqueQuantizer:
    """Current (A) to the float32 torque command (N m) and back, clamped at the current limit."""

    __slots__ = ("_kt", "_limit_A", "_limit_Nm")

    def __init__(self, current_limit_A: float, torque_constant_Nm_per_A: float) -> None:
        if not 0.0 < current_limit_A < math.inf:
            raise ConfigError("drive.current_limit_A", f"must be a finite number > 0, got {current_limit_A}")
        if not 0.0 < torque_constant_Nm_per_A < math.inf:
            raise ConfigError(
                "drive.odrive.torque_constant_Nm_per_A",
                f"must be a finite number > 0, got {torque_constant_Nm_per_A}",
            )
        self._kt = torque_constant_Nm_per_A
        self._limit_A = current_limit_A
        self._limit_Nm = self._to_torque(current_limit_A)

    @property
    def max_current_A(self) -> float:
        return self._limit_Nm / self._kt

    def _to_torque(self, current_A: float) -> float:
        """float32(current * kt), one ulp towards zero if it maps back beyond the limit."""
        torque = float(np.float32(current_A * self._kt))
        if abs(torque) / self._kt > self._limit_A:
            torque = float(np.nextafter(np.float32(torque), np.float32(0.0)))
        return torque

    def quantize(self, current_A: tuple[float, ...]) -> tuple[tuple[int, ...], tuple[float, ...], bool]:
        if len(current_A) != N_AXES:
            raise ProtocolError(f"current_A: the ODrive profile drives 1 axis, got {len(current_A)} currents")
        u = current_A[0]
        if not -math.inf < u < math.inf:
            return (0,), (0.0,), True
        saturated = False
        if u > self._limit_A:
            torque, saturated = self._limit_Nm, True
        elif u < -self._limit_A:
            torque, saturated = -self._limit_Nm, True
        else:
            torque = self._to_torque(u)
        return (_BITS.unpack(_F32.pack(torque))[0],), (torque / self._kt,), saturated

    def torque_of(self, code: int) -> tuple[float, bool]:
        """(torque in N m, clamped) of a command code; a non-finite pattern gives (0.0, True)."""
        torque = float(_F32.unpack(_BITS.pack(code))[0])
        if not math.isfinite(torque):
            return 0.0, True
        if torque > self._limit_Nm:
            return self._limit_Nm, True
        if torque < -self._limit_Nm:
            return -self._limit_Nm, True
        return torque, False


class OdriveDriveLink(ClosingLink):
    """One ODrive axis on a python-can bus. See the module docstring."""

    n_axes: Final = N_AXES

    def __init__(
        self,
        bus: can.BusABC,
        drive: DriveConfig,
        options: OdriveOptions,
        period_ns: int,
        *,
        frame_hook: FrameHook | None = None,
        event_hook: EventHook | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        owns_bus: bool = False,
        send_timeout_ns: int | None = None,
    ) -> None:
        if drive.profile != "odrive":
            raise ConfigError(
                "drive.profile", f"OdriveDriveLink drives the odrive profile, got {drive.profile!r}"
            )
        if not drive.encoder_counts_per_unit > 0.0:
            raise ConfigError(
                "drive.encoder_counts_per_unit", f"must be > 0, got {drive.encoder_counts_per_unit}"
            )
        try:
            self._ids = {cmd: codec.arbitration_id(drive.node_id, cmd) for cmd in CmdId}
        except ProtocolError as exc:
            raise ConfigError("drive.node_id", str(exc)) from None
        self._quantizer = TorqueQuantizer(drive.current_limit_A, options.torque_constant_Nm_per_A)
        self._estimates_id = self._ids[CmdId.GET_ENCODER_ESTIMATES]
        self._heartbeat_id = self._ids[CmdId.HEARTBEAT]
        self._torque_id = self._ids[CmdId.SET_INPUT_TORQUE]
        self._own_tx_ids = frozenset(
            self._ids[c]
            for c in (
                CmdId.SET_AXIS_STATE,
                CmdId.SET_CONTROLLER_MODE,
                CmdId.SET_INPUT_TORQUE,
                CmdId.CLEAR_ERRORS,
            )
        )
        self._bus = bus
        self._drive = drive
        self._options = options
        self._node = drive.node_id
        self._period_ns = period_ns
        self._cpr = options.encoder_cpr
        self._counts_per_unit = drive.encoder_counts_per_unit
        self._frame_hook = frame_hook
        self._event_hook = event_hook
        self._clock_ns = clock_ns
        self._owns_bus = owns_bus
        self._send_timeout_s = None if send_timeout_ns is None else send_timeout_ns * 1e-9
        self.stats = OdriveLinkStats()
        self._seq: int | None = None
        self._last_stamp_ns = 0
        self._last_data: bytes | bytearray = b""
        self._lockstep = False  # set by enable_lockstep: one estimate per sample, no wall clock
        self._rtr_mode = options.encoder_msg_rate_ms == 0  # host-clocked: estimates only on RTR
        self._triggers = 0  # RTR triggers sent
        self._answered = True  # the last trigger was answered (a second answer is stale)
        self._heartbeat: codec.Heartbeat | None = None
        self._armed = False  # enabled: a heartbeat with errors or out of closed loop ends the run
        self._enable_attempt = False
        self._enable_seen = False
        self._pending: Feedback | None = None
        self._closed = False
        self.fast = FAST_PATH  # the per-period fast paths (receive, quantize, command), same results
        self._kt = options.torque_constant_Nm_per_A
        self._limit_A = drive.current_limit_A
        self._q_codes: tuple[int, ...] | None = None  # the codes quantize returned last ...
        self._q_payload = b""  # ... and their Set_Input_Torque payload
        self._q_high = self._saturated(math.inf)  # (quantize's result, payload) beyond +limit
        self._q_low = self._saturated(-math.inf)  # ... and beyond -limit
        self._rtr: can.Message | None = None  # lockstep: the RTR trigger, sent again every period
        self._fast_answer_id = -1  # lockstep, host-clocked, fast: the estimates' id (_estimates_fast)
        self._hb_enabled = False  # the last heartbeat shows closed loop without errors
        self._hb_fault = False  # ... shows axis errors
        self._hb_raw = b""  # the last heartbeat's payload (decoded: _heartbeat)

    # --- DriveLink ---------------------------------------------------------------------------------
    @property
    def current_limit_A(self) -> float:
        return self._drive.current_limit_A

    @property
    def heartbeat(self) -> codec.Heartbeat | None:
        """The last heartbeat received (None before the first)."""
        return self._heartbeat

    def receive_feedback(self, timeout_ns: int) -> Feedback | None:
        if self._closed:
            self._check_open()
        recv = self._bus.recv
        if timeout_ns <= 0:
            msg = recv(0.0)
            reads = 1
            if (  # the answer to the trigger, first in the queue (the per-period path): _consume, inline
                msg is not None
                and msg.arbitration_id == self._fast_answer_id
                and not (msg.is_error_frame or msg.is_extended_id or msg.is_remote_frame)
            ):
                now_ns = self._clock_ns()
                if self._frame_hook is not None:
                    self._frame_hook(msg, True)
                self.stats.rx_frames += 1
                if not self._estimates_fast(msg, now_ns):
                    self._consume_general(msg, now_ns)
                answer = self._pending
                if answer is not None:
                    self._pending = None
                    return answer
                msg = recv(0.0)
                reads += 1
            while msg is not None:
                self._consume(msg)
                if self._pending is not None or reads >= MAX_READS_AFTER_DEADLINE:
                    break
                msg = recv(0.0)
                reads += 1
            fb, self._pending = self._pending, None  # _take, inline (the per-period path)
            return fb
        deadline_ns = time.monotonic_ns() + timeout_ns
        while self._pending is None:
            remaining_ns = deadline_ns - time.monotonic_ns()
            msg = recv(max(remaining_ns, 0) * 1e-9)
            if msg is None:
                break
            self._consume(msg)
            if remaining_ns <= 0:
                break
        return self._take()

    def _take(self) -> Feedback | None:
        fb, self._pending = self._pending, None
        return fb

    def quantize(self, current_A: tuple[float, ...]) -> tuple[tuple[int, ...], tuple[float, ...], bool]:
        if self.fast and len(current_A) == N_AXES:
            # TorqueQuantizer.quantize for a current within the limit, in one call: the float32
            # rounding by struct (the same C cast as numpy's); its bytes are the command's payload
            u = current_A[0]
            limit_A, kt = self._limit_A, self._kt
            if limit_A < u < _INF:  # saturated: the limit's command, computed once
                result, self._q_payload = self._q_high
                self._q_codes = result[0]
                return result
            if -_INF < u < -limit_A:
                result, self._q_payload = self._q_low
                self._q_codes = result[0]
                return result
            if -limit_A <= u <= limit_A:
                try:
                    raw = _F32.pack(u * kt)
                except OverflowError:  # beyond float32 (an absurd limit): the general path
                    raw = b""
                if raw:
                    torque, code = _F32_AND_BITS.unpack(raw * 2)  # the float32 and its bit pattern
                    if abs(torque) / kt <= limit_A:  # else one ulp towards zero: the general path
                        codes = (code,)
                        self._q_codes, self._q_payload = codes, raw + _PAD4
                        return codes, (torque / kt,), False
        result = self._quantizer.quantize(current_A)
        if result[2] and not -math.inf < current_A[0] < math.inf:
            self.stats.nonfinite_currents += 1
            self._event(
                self._clock_ns(),
                LinkEventKind.INVALID_COMMAND,
                f"node {self._node}: non-finite current {current_A[0]!r} A requested; 0 N m sent instead",
            )
        return result

    def _saturated(self, sign: float) -> tuple[tuple[tuple[int, ...], tuple[float, ...], bool], bytes]:
        """(quantize's result, Set_Input_Torque payload) of a current beyond the limit (``sign``'s sign)."""
        result = self._quantizer.quantize((math.copysign(2.0 * self._limit_A, sign),))
        torque, _ = self._quantizer.torque_of(result[0][0])
        return result, _TORQUE.pack(torque)

    def send_command(self, codes: tuple[int, ...], answers_seq: int) -> int:
        """Set_Input_Torque of ``codes[0]`` (a float32 bit pattern, clamped at the limit)."""
        if codes is self._q_codes:  # what quantize just returned: finite, clamped at the limit
            if self._closed:
                self._check_open()
            msg = data_frame(0.0, self._torque_id, self._q_payload)  # 8 bytes: DLC
            self._send_message(msg, "Set_Input_Torque")
            return self._clock_ns()
        if len(codes) != N_AXES:
            raise ProtocolError(f"Set_Input_Torque: the ODrive profile drives 1 axis, got {len(codes)} codes")
        try:
            torque, clamped = self._quantizer.torque_of(codes[0])
        except (struct.error, TypeError):
            raise ProtocolError(f"Set_Input_Torque: expected an int32 code, got {codes[0]!r}") from None
        if clamped:
            self.stats.clamped_commands += 1
        self._send(self._torque_id, _TORQUE.pack(torque), "Set_Input_Torque")
        return self._clock_ns()

    def send_sync(self) -> int:
        """RTR Get_Encoder_Estimates, the trigger of the next sample: the drive answers with the
        estimates sampled on its arrival, which get the trigger's index as sequence number (with
        ``encoder_msg_rate_ms = 0``). Frames still queued are read (and judged) first."""
        if self._closed:
            self._check_open()
        recv = self._bus.recv
        while (msg := recv(0.0)) is not None:  # drain, inline
            self._consume(msg)
        self._pending = None  # an answer not taken before the next trigger is late: not a sample
        rtr = self._rtr
        if rtr is None or not self._lockstep:
            rtr = can.Message(0.0, self._estimates_id, False, True, False, None, codec.DLC, None)
            if self._lockstep and self.fast:  # one RTR for every trigger: it has no data and
                self._rtr = rtr  # nothing on the lockstep path changes a frame once sent
        self._send_message(rtr, "Get_Encoder_Estimates (RTR)")
        self._triggers += 1
        self._answered = False
        return self._clock_ns()

    send_trigger = send_sync  # the host-clocked runner's name for it

    def drain(self) -> None:
        """Read and judge the frames already queued, without blocking (host-clocked runners)."""
        while (msg := self._bus.recv(0.0)) is not None:
            self._consume(msg)

    def describe_fault(self, wait_ns: int = 0) -> str:
        """The last heartbeat's account of the drive's state and axis errors (for the exit reason)."""
        if wait_ns > 0:
            self.receive_feedback(wait_ns)
        hb = self._heartbeat
        return "no heartbeat" if hb is None else describe_heartbeat(hb)

    # --- enable / stop ---------------------------------------------------------------------------
    def request_enable(self) -> None:
        """Clear_Errors (if configured), Set_Controller_Mode torque/passthrough, request closed loop."""
        self._armed = False
        self._enable_attempt = True
        self._enable_seen = False
        if self._drive.clear_fault:  # [drive] clear_fault, or dob-hil run --clear-fault
            self._send(self._ids[CmdId.CLEAR_ERRORS], codec.encode_clear_errors(0), "Clear_Errors")
        self._send(
            self._ids[CmdId.SET_CONTROLLER_MODE],
            codec.encode_set_controller_mode(ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH),
            "Set_Controller_Mode",
        )
        self._send(self._torque_id, _TORQUE.pack(0.0), "Set_Input_Torque 0")
        self._request_state(AxisState.CLOSED_LOOP_CONTROL)

    def poll_enabled(self) -> bool:
        """Read the frames already queued; True once a heartbeat since the request shows closed loop."""
        while True:
            msg = self._bus.recv(0.0)
            if msg is None:
                break
            self._consume(msg)
        return self._attempt_result()

    def _attempt_result(self) -> bool:
        if self._enable_seen:
            self._enable_attempt = False
            self._armed = True
            return True
        return False

    def enable(self, timeout_ns: int, retry_interval_ns: int = 200_000_000) -> None:
        """request_enable(), then wait for the heartbeat; the request is repeated every
        ``retry_interval_ns`` (a lost frame, a drive that came up later). DriveFault on timeout,
        naming the axis state and error bits of the last heartbeat."""
        self._check_open()
        deadline_ns = time.monotonic_ns() + timeout_ns
        next_request_ns = 0
        while True:
            now = time.monotonic_ns()
            if now >= next_request_ns:
                self.request_enable()
                next_request_ns = now + retry_interval_ns
            wait_ns = min(deadline_ns, next_request_ns) - time.monotonic_ns()
            msg = self._bus.recv(max(wait_ns, 0) * 1e-9)
            if msg is not None:
                self._consume(msg)
                self._pending = None  # estimates before closed loop are not samples
            if self._attempt_result():
                return
            if time.monotonic_ns() >= deadline_ns:
                if self.poll_enabled():
                    return
                raise self._not_enabled(f"within {timeout_ns / 1e6:g} ms")

    def enable_lockstep(self, service: Callable[[], int], max_rounds: int = 3) -> None:
        """Enable against the embedded lockstep drive; from now on each estimate is one sample."""
        self._lockstep = True
        if self.fast and self._rtr_mode:
            self._fast_answer_id = self._estimates_id
        self.request_enable()
        for _ in range(max_rounds):
            service()
            if self.poll_enabled():
                return
        raise self._not_enabled(f"after {max_rounds} rounds of the simulated drive")

    def _not_enabled(self, when: str) -> DriveFault:
        self._enable_attempt = False
        hb = self._heartbeat
        last = "no heartbeat" if hb is None else f"last heartbeat: {describe_heartbeat(hb)}"
        return DriveFault(f"node {self._node}: the ODrive did not enter CLOSED_LOOP_CONTROL {when} ({last})")

    def _request_state(self, state: AxisState) -> None:
        self._send(
            self._ids[CmdId.SET_AXIS_STATE],
            codec.encode_set_axis_state(state),
            f"Set_Axis_State {state.name}",
        )

    def safe_stop(self) -> None:
        """Set_Input_Torque 0, then Set_Axis_State IDLE; each attempted. Never raises; repeatable."""
        if self._closed:
            return
        self._armed = False
        self._enable_attempt = False
        self._stop_step(
            "Set_Input_Torque 0",
            lambda: self._send(self._torque_id, _TORQUE.pack(0.0), "Set_Input_Torque (stop)"),
        )
        self._stop_step("Set_Axis_State IDLE", lambda: self._request_state(AxisState.IDLE))

    # --- receiving ---------------------------------------------------------------------------------
    def _consume(self, msg: can.Message) -> None:
        now_ns = self._clock_ns()
        if self._frame_hook is not None:
            self._frame_hook(msg, True)
        self.stats.rx_frames += 1
        if (
            msg.arbitration_id == self._fast_answer_id
            and not (msg.is_error_frame or msg.is_extended_id or msg.is_remote_frame)
            and self._estimates_fast(msg, now_ns)
        ):
            return
        self._consume_general(msg, now_ns)

    def _consume_general(self, msg: can.Message, now_ns: int) -> None:
        """A received frame that is not the common answer (logged and counted already)."""
        if msg.is_error_frame:
            self.stats.error_frames += 1
            self._event(now_ns, LinkEventKind.ERROR_FRAME, f"error frame {_describe(msg)}")
            return
        aid = msg.arbitration_id
        if msg.is_extended_id:
            self._foreign(now_ns, msg)
            return
        if aid == self._estimates_id:
            if msg.is_remote_frame:
                self.stats.own_echoes += 1  # our own trigger, echoed back
                return
            self._on_estimates(msg, now_ns)
        elif aid == self._heartbeat_id and not msg.is_remote_frame:
            self._on_heartbeat(msg, now_ns)
        elif aid in self._own_tx_ids and not msg.is_remote_frame:
            self.stats.own_echoes += 1
        else:
            self._foreign(now_ns, msg)

    def _on_estimates(self, msg: can.Message, now_ns: int) -> None:
        data = msg.data
        if len(data) != codec.DLC:
            self._malformed(
                now_ns, msg, f"Get_Encoder_Estimates: expected {codec.DLC} bytes, got {len(data)}"
            )
            return
        pos_turns, vel = _ESTIMATES.unpack(data)
        if not (-math.inf < pos_turns < math.inf and -math.inf < vel < math.inf):
            self.stats.nonfinite_estimates += 1
            self._malformed(
                now_ns, msg, f"non-finite encoder estimate (pos {pos_turns!r} turns, vel {vel!r} turns/s)"
            )
            return
        counts = round(pos_turns * self._cpr)
        if not -MAX_COUNTS <= counts <= MAX_COUNTS:
            self._malformed(
                now_ns, msg, f"encoder estimate {pos_turns!r} turns is beyond the int32 count range"
            )
            return
        # lockstep: the simulated drive's stamps (0.0 at t = 0); real time: the bus timestamp
        stamp_s = msg.timestamp if self._lockstep else msg.timestamp or time.time()
        stamp_ns = round(stamp_s * 1e9)
        last_seq = self._seq
        if last_seq is not None:
            gap_ns = stamp_ns - self._last_stamp_ns
            if gap_ns < 0 or (gap_ns == 0 and bytes(data) == self._last_data):
                what = "a duplicate" if gap_ns == 0 else f"{-gap_ns / 1e6:.3f} ms older than the last"
                self._stale(now_ns, what)
                return
        if self._rtr_mode:  # the answer to the last trigger, numbered by it
            if self._answered or self._triggers == 0:
                self._stale(now_ns, "not asked for (no RTR outstanding)")
                return
            self._answered = True
            seq = (self._triggers - 1) % SEQ_MODULO
            if last_seq is not None and (seq - last_seq) % SEQ_MODULO > 1:
                self.stats.missed_feedback += (seq - last_seq) % SEQ_MODULO - 1
        elif last_seq is None:
            seq = 0
        else:  # cyclic: numbered by the time since the last one
            step = 1 if self._lockstep else max(1, round(gap_ns / self._period_ns))
            if step > 1:
                self.stats.missed_feedback += step - 1
            seq = (last_seq + step) % SEQ_MODULO
        self._last_stamp_ns = stamp_ns
        self._last_data = bytes(data)
        self._seq = seq
        hb = self._heartbeat
        enabled = hb is not None and hb.axis_state == _CLOSED_LOOP and hb.axis_error == 0
        fault = hb is not None and hb.axis_error != 0
        self.stats.feedback += 1
        self._pending = Feedback(
            now_ns, seq, (counts,), (counts,), (counts / self._counts_per_unit,), enabled, fault, False
        )

    def _estimates_fast(self, msg: can.Message, now_ns: int) -> bool:
        """:meth:`_on_estimates` for the common lockstep case: the one answer to the last RTR, well
        formed, after the first; False (nothing done) for anything else, which takes the general path."""
        data = msg.data
        last_seq = self._seq
        if self._answered or last_seq is None or len(data) != _DLC:
            return False
        pos_turns, vel = _ESTIMATES.unpack(data)
        if not (-_INF < pos_turns < _INF and -_INF < vel < _INF):
            return False
        counts = round(pos_turns * self._cpr)
        if not -MAX_COUNTS <= counts <= MAX_COUNTS:
            return False
        stamp_ns = round(msg.timestamp * 1e9)
        gap_ns = stamp_ns - self._last_stamp_ns
        if gap_ns < 0 or (gap_ns == 0 and data == self._last_data):
            return False  # stale: the general path names it
        self._answered = True
        seq = (self._triggers - 1) % SEQ_MODULO
        skipped = (seq - last_seq) % SEQ_MODULO
        if skipped > 1:
            self.stats.missed_feedback += skipped - 1
        self._last_stamp_ns = stamp_ns
        self._last_data = data  # the frame's own bytes: nothing changes a frame once received
        self._seq = seq
        self.stats.feedback += 1
        count_t = (counts,)
        position = (counts / self._counts_per_unit,)
        # Feedback(...) without NamedTuple's Python-level __new__ (the per-period path)
        fb = (now_ns, seq, count_t, count_t, position, self._hb_enabled, self._hb_fault, False)
        self._pending = tuple.__new__(Feedback, fb)
        return True

    def _stale(self, now_ns: int, what: str) -> None:
        self.stats.stale_feedback += 1
        self._event(
            now_ns, LinkEventKind.STALE_FEEDBACK, f"node {self._node}: encoder estimates {what}; discarded"
        )

    def _on_heartbeat(self, msg: can.Message, now_ns: int) -> None:
        old = self._heartbeat
        raw = bytes(msg.data)
        if old is not None and raw == self._hb_raw:
            hb = old  # the same payload as the last heartbeat: the same decoded heartbeat
        else:
            try:
                hb = codec.decode_heartbeat(raw)
            except ProtocolError as exc:
                self._malformed(now_ns, msg, str(exc))
                return
            self._hb_raw = raw
        self.stats.heartbeats += 1
        self._heartbeat = hb
        self._hb_enabled = hb.axis_state == _CLOSED_LOOP and hb.axis_error == 0  # for _estimates_fast
        self._hb_fault = hb.axis_error != 0
        if old is None or (old.axis_state, old.axis_error) != (hb.axis_state, hb.axis_error):
            before = "unknown" if old is None else old.axis_state.name
            self._event(
                now_ns, LinkEventKind.DRIVE_STATE, f"node {self._node}: {before} -> {describe_heartbeat(hb)}"
            )
        if hb.axis_error:
            self.stats.axis_errors += 1
            if old is None or old.axis_error != hb.axis_error:
                self._event(
                    now_ns,
                    LinkEventKind.DRIVE_FAULT,
                    f"node {self._node}: axis error {describe_heartbeat(hb)}",
                )
        if self._enable_attempt and hb.axis_state == _CLOSED_LOOP and hb.axis_error == 0:
            self._enable_seen = True
        if self._armed and (hb.axis_error or hb.axis_state != _CLOSED_LOOP):
            self._armed = False
            raise DriveFault(f"node {self._node}: the ODrive left closed loop: {describe_heartbeat(hb)}")

    def _foreign(self, now_ns: int, msg: can.Message) -> None:
        self.stats.foreign_frames += 1
        self._event(
            now_ns,
            LinkEventKind.FOREIGN_FRAME,
            f"{_describe(msg)} is not a frame of ODrive node {self._node}; skipped",
        )

    def _malformed(self, now_ns: int, msg: can.Message, problem: str) -> None:
        self.stats.malformed_frames += 1
        self._event(now_ns, LinkEventKind.MALFORMED_FRAME, f"{_describe(msg)} skipped: {problem}")

    def _event(self, time_ns: int, kind: LinkEventKind, message: str) -> None:
        if self._event_hook is not None:
            self._event_hook(LinkEvent(time_ns, kind, message))

    # --- sending -----------------------------------------------------------------------------------
    def _send_failed(self, msg: can.Message, what: str, exc: can.CanError) -> DriveFault:
        """Count and report a send the bus refused; the DriveFault to raise."""
        self.stats.send_failures += 1
        text = f"node {self._node}: sending {what} (id 0x{msg.arbitration_id:03X}) failed: {exc}"
        self._event(self._clock_ns(), LinkEventKind.SEND_FAILED, text)
        return DriveFault(text)

    def _send(self, arbitration_id: int, payload: bytes, what: str, *, remote: bool = False) -> None:
        self._check_open()
        data = None if remote else payload
        msg = can.Message(0.0, arbitration_id, False, remote, False, None, codec.DLC, data)
        self._send_message(msg, what)

    def _send_message(self, msg: can.Message, what: str) -> None:
        """Send ``msg`` (the link is open), count it and log it; DriveFault if the bus refuses it."""
        try:
            self._bus.send(msg, self._send_timeout_s)
        except can.CanError as exc:
            raise self._send_failed(msg, what, exc) from exc
        self.stats.tx_frames += 1
        if self._frame_hook is not None:
            self._frame_hook(msg, False)


def _describe(msg: can.Message) -> str:
    if msg.is_error_frame:
        return f"(error class 0x{msg.arbitration_id:X}, data {bytes(msg.data).hex() or '-'})"
    width = 8 if msg.is_extended_id else 3
    rtr = " RTR" if msg.is_remote_frame else ""
    return f"id 0x{msg.arbitration_id:0{width}X}{rtr} DLC {msg.dlc} data {bytes(msg.data).hex() or '-'}"


__all__ = ["OdriveDriveLink", "OdriveLinkStats", "TorqueQuantizer", "describe_heartbeat"]
