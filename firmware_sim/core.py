"""The drive firmware's logic, independent of any clock: frames in, frames and samples out.

A clock (:mod:`firmware_sim.lockstep` or :mod:`firmware_sim.realtime`) feeds received frames to
:meth:`DriveCore.on_frame` with their instant, advances the physics with
:meth:`DriveCore.integrate_to`, closes periods with :meth:`DriveCore.period_boundary` and takes
a feedback sample with :meth:`DriveCore.sample`. Frames the firmware sends on its own (FAULT,
HEARTBEAT) queue up for :meth:`DriveCore.take_outgoing`. Times are simulated nanoseconds
since the simulation started.

Behaviour: the drive side of ``docs/PROTOCOL.md`` (version 2); the section names below are its.

* CONTROL requests of our protocol version drive the state machine
  (:mod:`firmware_sim.state_machine`); every CONTROL frame is answered by a HEARTBEAT with the
  resulting state and the drive's version (a refused enable in FAULT says FAULT; a request of
  another version is not acted on). Leaving ENABLED zeroes the current at once. Heartbeats also
  go out every 100 ms.
* A COMMAND is *valid* if it answers a feedback sequence within the acceptance window (the last
  sample in lockstep; the last ``min(watchdog_periods, 64)`` samples, at least 2, in real time)
  newer than the last accepted one: a late command still acts, a duplicate or older one is stale.
  Only valid commands feed the watchdog. While ENABLED the DAC code is
  clamped at the limit (status SATURATED) and acts ``input_delay_samples`` periods later. A
  command with the enable bit clear commands zero current, valid or stale (a stop is never
  stale); the drive **stays ENABLED** (the bit gates the current, the CONTROL frame owns the
  state). Commands while DISABLED or in FAULT apply nothing.
* A frame with our COMMAND/CONTROL id that does not decode (too short, unknown request) faults
  the drive: FAULT frame ``BAD_FRAME`` with the id's low byte. Frames padded to 8 bytes decode.
* The watchdog is armed by the first valid command after entering ENABLED; armed, the
  ``watchdog_periods``-th period in a row without a valid command faults the drive: FAULT frame
  ``WATCHDOG`` (info = periods, capped at 255) and status FAULT|WATCHDOG until CLEAR_FAULT. Not
  armed, it allows :data:`FIRST_COMMAND_TIMEOUT_NS` (at least ``2 watchdog_periods``), then faults
  ``WATCHDOG`` with info 0.
* A plant position the encoder cannot represent (non-finite, or the physics overflowing) faults
  the drive with ``ENCODER``.
* Disturbances start at the first enable (their t = 0), so every run starts from rest.
* :class:`~firmware_sim.behaviour.DriveBehaviour` selects the variants the spec permits
  (sequence restart on enable, FAULT on a COMMAND while DISABLED, padded frames) and two
  deliberate violations.
* A FAULT frame is sent when the drive enters FAULT, followed by a HEARTBEAT, and again before
  every periodic HEARTBEAT while in FAULT (a host started later learns the code and info).
* Injected faults (``[sim.faults]``, :mod:`firmware_sim.faults`): a FAULT at period N, silence
  from period N (:attr:`DriveCore.silent`: the clocks send nothing), an encoder jump at period N.
* FEEDBACK status: ENABLED, SATURATED (the last applied command was clamped), FAULT, WATCHDOG
  (the fault is the watchdog's). The sequence counts samples mod 256, lost ones included.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Callable
from dataclasses import dataclass

from dob_hil.config import Config
from dob_hil.errors import ConfigError, ProtocolError
from dob_hil.link.protocol import (
    COMMAND_SEQ_MODULO,
    DLC,
    HEARTBEAT_PERIOD_NS,
    MAX_PADDED_LEN,
    SEQ_MODULO,
    ControlRequest,
    DriveState,
    FaultCode,
    FaultFrame,
    FeedbackFrame,
    FrameKind,
    HeartbeatFrame,
    Status,
    decode_command,
    decode_control,
    encode_fault,
    encode_feedback,
    encode_heartbeat,
    frame_id,
)
from firmware_sim.actuator import CurrentPath
from firmware_sim.behaviour import REFERENCE, DriveBehaviour
from firmware_sim.dac import Dac
from firmware_sim.disturbance import Disturbance
from firmware_sim.encoder import Encoder
from firmware_sim.faults import DriveFaults
from firmware_sim.plant import PlantModel, check_single_axis
from firmware_sim.state_machine import DriveStateMachine
from firmware_sim.truth import GroundTruth
from firmware_sim.watchdog import CommandWatchdog

REALTIME_ACCEPT_WINDOW_MAX = 64  # half the 7-bit command sequence space
FIRST_COMMAND_TIMEOUT_NS = 1_000_000_000  # enabled without a first valid command: WATCHDOG (info 0)
_PADDING = bytes(MAX_PADDED_LEN)
_COMMAND_STRUCT = struct.Struct("<hB")  # protocol.COMMAND: i16 current, u8 seq7 | enable << 7
_COMMAND_DLC = DLC[FrameKind.COMMAND]
_FEEDBACK_STRUCT = struct.Struct("<iBB")  # protocol.FEEDBACK: i32 counts, u8 seq, u8 status
_ST_OFF = 0  # plain ints: struct packs them without Status.__index__
_ST_ENABLED = int(Status.ENABLED)
_ST_ENABLED_SATURATED = int(Status.ENABLED | Status.SATURATED)
_ST_FAULT = int(Status.FAULT)
_ST_FAULT_WATCHDOG = int(Status.FAULT | Status.WATCHDOG)

OutgoingFrame = tuple[FrameKind, bytes]
_new_tuple = tuple.__new__
TruthSink = Callable[[GroundTruth], None]


class FrameResult(enum.Enum):
    IGNORED = "ignored"  # not a frame for this drive
    CONTROL = "control"
    COMMAND = "command"  # a valid command
    STALE_COMMAND = "stale_command"  # answers no recent feedback, or a duplicate
    BAD_FRAME = "bad_frame"  # our id, but does not decode


@dataclass
class DriveStats:
    """Counters of what the drive saw and did."""

    samples: int = 0
    feedback_sent: int = 0
    feedback_lost: int = 0
    commands_accepted: int = 0
    commands_stale: int = 0
    bad_frames: int = 0
    frames_ignored: int = 0
    saturations: int = 0
    overruns: int = 0  # real time: sample instants skipped because the timer fell behind
    send_failures: int = 0
    frames_suppressed: int = 0  # not sent because the drive is silent ([sim.faults] silent_at_s)
    rx_errors: int = 0  # frames the bus could not deliver (bus.recv raised)
    version_mismatches: int = 0  # CONTROL requests of another protocol version, not acted on
    stops: int = 0  # COMMANDs with the enable bit clear acted on while ENABLED


class DriveCore:
    def __init__(
        self,
        config: Config,
        *,
        accept_window: int,
        want_truth: bool,
        behaviour: DriveBehaviour = REFERENCE,
        plant_model: PlantModel | None = None,
        disturbance: Disturbance | None = None,
    ) -> None:
        """``plant_model``, ``disturbance``: given by a drive of several axes (firmware_sim.axes),
        whose axes share one coupled plant: this core reads its axis's output from it, sets the
        disturbance's origin at its first enable, and never integrates (the multi-axis core does)."""
        if plant_model is None:
            check_single_axis(config.plant)
        self.behaviour = behaviour
        self.version = behaviour.protocol_version
        drive, sim, plant = config.drive, config.sim, config.plant
        self.node_id = drive.node_id
        try:
            self.command_id = frame_id(FrameKind.COMMAND, drive.node_id)
        except ProtocolError as exc:
            raise ConfigError("drive.node_id", str(exc).removeprefix("node_id: ")) from None
        self.control_id = frame_id(FrameKind.CONTROL, drive.node_id)
        self.period_ns = plant.period_ns
        self.delay_ns = plant.input_delay_samples * plant.period_ns
        self.accept_window = accept_window
        self.want_truth = want_truth
        if disturbance is None:
            disturbance = Disturbance(sim.disturbances, plant.period_s / sim.substeps)
            disturbance.origin_s = None  # zero until the first enable
        self.disturbance = disturbance
        self.plant = plant_model or PlantModel(plant, sim.substeps, self.disturbance, sim.initial_state)
        self.dac = Dac(drive.dac_lsb_A, drive.current_limit_A)
        self._dac_limit = self.dac.limit_counts  # the per-period path clamps inline (Dac.convert)
        self._dac_lsb_A = self.dac.lsb_A
        self.encoder = Encoder(
            drive.encoder_counts_per_unit, drive.encoder_bits, sim.noise_counts_std, sim.seed
        )
        self.machine = DriveStateMachine()
        self.watchdog = CommandWatchdog(
            drive.watchdog_periods, -(-FIRST_COMMAND_TIMEOUT_NS // plant.period_ns)
        )
        self.path = CurrentPath()
        self.stats = DriveStats()
        self.time_ns = 0  # the physics has been integrated up to here
        self.saturated = False  # the last applied command was clamped
        self._samples = 0  # feedback samples taken; the sequence is (this - _seq_origin) mod 256
        self._seq_origin = 0  # sample number of sequence 0 (moves on enable with restart_sequence)
        self._physics_ok = True  # False once the physics overflowed (ENCODER fault)
        self._fault_payload = b""  # the FAULT frame of the current fault
        self._pad = behaviour.pad_frames
        self._last_accepted = -1  # sample number answered by the last valid command
        self._next_heartbeat_ns = HEARTBEAT_PERIOD_NS
        self._out: list[OutgoingFrame] = []
        self.faults = DriveFaults.from_config(config)  # injected faults ([sim.faults]); None: none
        self.silent = False  # set by an injected fault: the clocks send nothing

    # --- state ---------------------------------------------------------------------------------
    @property
    def state(self) -> DriveState:
        return self.machine.state

    @property
    def period_index(self) -> int:
        return self.time_ns // self.period_ns

    @property
    def last_seq(self) -> int | None:
        """The sequence number of the last feedback sample, None before the first."""
        return (self._samples - 1 - self._seq_origin) % SEQ_MODULO if self._samples else None

    def take_outgoing(self) -> list[OutgoingFrame]:
        out, self._out = self._out, []
        if self._pad:
            return [(kind, payload + _PADDING[len(payload) :]) for kind, payload in out]
        return out

    def _heartbeat(self, state: DriveState) -> OutgoingFrame:
        return FrameKind.HEARTBEAT, encode_heartbeat(HeartbeatFrame(state, self.version))

    # --- frames --------------------------------------------------------------------------------
    def on_frame(self, arbitration_id: int, data: bytes | bytearray, t_ns: int) -> FrameResult:
        """Act on a received frame at simulated time ``t_ns`` (>= :attr:`time_ns`)."""
        if arbitration_id == self.command_id:
            if len(data) == _COMMAND_DLC:  # the per-period fast path: the codec's layout, no objects
                current_counts, tail = _COMMAND_STRUCT.unpack(data)
                return self._on_command(current_counts, tail & 0x7F, bool(tail & 0x80), t_ns)
            try:
                cmd = decode_command(data)  # raises, naming what is wrong
            except ProtocolError:
                return self._bad_frame(arbitration_id, t_ns)
            return self._on_command(cmd.current_counts, cmd.seq, cmd.enable, t_ns)
        if arbitration_id == self.control_id:
            try:
                control = decode_control(data)
            except ProtocolError:
                return self._bad_frame(arbitration_id, t_ns)
            if control.version != self.version:  # not acted on; the heartbeat names our version
                self.stats.version_mismatches += 1
                self._out.append(self._heartbeat(self.machine.state))
                return FrameResult.CONTROL
            self._on_control(control.request, t_ns)
            return FrameResult.CONTROL
        self.stats.frames_ignored += 1
        return FrameResult.IGNORED

    def _answered_sample(self, seq7: int) -> int | None:
        last = self._samples - 1
        if last < 0:
            return None
        s = last - ((last - self._seq_origin - seq7) % COMMAND_SEQ_MODULO)
        if last - s >= self.accept_window or s <= self._last_accepted:
            return None
        return s

    def lockstep_period(self, current_counts: int, seq7: int) -> bool:
        """Lockstep's per-period path in one call: an enabling COMMAND at :attr:`time_ns` and the
        commanded period (``on_frame`` + ``integrate_to`` + ``period_boundary(True)``, with the
        same effects); the caller sends what is queued and takes the :meth:`sample`. Only for the
        common case: ENABLED, no injected faults, a valid answer, no current change pending, no
        input delay, no heartbeat due in the period; otherwise False, with nothing changed (the
        caller takes the general path)."""
        last = self._samples - 1
        s = last - ((last - self._seq_origin - seq7) % COMMAND_SEQ_MODULO)
        path = self.path
        t = self.time_ns
        t_end = t + self.period_ns
        if (
            last < 0
            or last - s >= self.accept_window
            or s <= self._last_accepted
            or self.machine.state is not DriveState.ENABLED
            or self.faults is not None
            or self.delay_ns
            or path.pending
            or t_end >= self._next_heartbeat_ns
            or not self._physics_ok
        ):
            return False
        self._last_accepted = s
        stats = self.stats
        stats.commands_accepted += 1
        limit = self._dac_limit  # Dac.convert, inline
        code = limit if current_counts > limit else -limit if current_counts < -limit else current_counts
        applied_A = code * self._dac_lsb_A
        self.saturated = saturated = code != current_counts
        if saturated:
            stats.saturations += 1
        path.held_A = applied_A  # path.schedule(t) + apply_due(t): nothing else is pending
        try:
            self.plant.advance(t, t_end, applied_A)
            self.time_ns = t_end
        except (OverflowError, ValueError, FloatingPointError):  # as integrate_to
            self._physics_ok = False
            self.fault(FaultCode.ENCODER, 0, self.time_ns)
            self.time_ns = max(self.time_ns, t_end)
        if self.machine.state is DriveState.ENABLED:  # period_boundary(True), no heartbeat due
            self.watchdog.armed = True
            self.watchdog.missed = 0
        return True

    def _on_command(self, current_counts: int, seq7: int, enable: bool, t_ns: int) -> FrameResult:
        state = self.machine.state
        if state is DriveState.DISABLED and self.behaviour.fault_on_command_while_disabled:
            self.fault(FaultCode.COMMAND_WHILE_DISABLED, 0, t_ns)
        # _answered_sample, inline (the per-period path)
        last = self._samples - 1
        s = last - ((last - self._seq_origin - seq7) % COMMAND_SEQ_MODULO)
        if last < 0 or last - s >= self.accept_window or s <= self._last_accepted:
            self.stats.commands_stale += 1
            if not enable and state is DriveState.ENABLED and not self.behaviour.stale_stop_ignored:
                self._stop(t_ns)  # a stop is never stale (it does not feed the watchdog)
            return FrameResult.STALE_COMMAND
        self._last_accepted = s
        self.stats.commands_accepted += 1
        if self.machine.state is DriveState.ENABLED:
            if enable:
                # Dac.convert, inline: clamp at the limit, code * LSB
                limit = self._dac_limit
                if current_counts > limit:
                    code = limit
                elif current_counts < -limit:
                    code = -limit
                else:
                    code = current_counts
                applied_A = code * self._dac_lsb_A
                self.saturated = saturated = code != current_counts
                if saturated:
                    self.stats.saturations += 1
            else:
                self._stop(t_ns)
                return FrameResult.COMMAND
            self.path.schedule(t_ns + self.delay_ns, applied_A)
        return FrameResult.COMMAND

    def _stop(self, t_ns: int) -> None:
        self.stats.stops += 1
        self.saturated = False
        self.path.schedule(t_ns + self.delay_ns, 0.0)

    def _on_control(self, request: ControlRequest, t_ns: int) -> None:
        before = self.machine.state
        after = self.machine.request(request)
        if before is DriveState.ENABLED and after is not DriveState.ENABLED:
            self.path.cut(t_ns)
            self.saturated = False
        elif after is DriveState.ENABLED and before is not DriveState.ENABLED:
            self.watchdog.reset()
            self.saturated = False
            if self.disturbance.origin_s is None:  # the first enable: disturbances start now
                self.disturbance.origin_s = self.time_ns * 1e-9
                self.plant.disturbance_changed()
            if self.behaviour.restart_sequence_on_enable:
                self._seq_origin = self._samples
                self._last_accepted = self._samples - 1
            if self.faults is not None:
                self.faults.on_enabled(self.time_ns // self.period_ns)
        self._out.append(self._heartbeat(after))

    def _bad_frame(self, arbitration_id: int, t_ns: int) -> FrameResult:
        self.stats.bad_frames += 1
        self.fault(FaultCode.BAD_FRAME, arbitration_id & 0xFF, t_ns)
        return FrameResult.BAD_FRAME

    def fault(self, code: FaultCode, info: int, t_ns: int) -> None:
        """Enter FAULT (zero current, FAULT + HEARTBEAT frames); nothing if already in FAULT."""
        was_enabled = self.machine.state is DriveState.ENABLED
        if not self.machine.fault(code):
            return
        if was_enabled:
            self.path.cut(t_ns)
        self.saturated = False
        self._fault_payload = encode_fault(FaultFrame(code, min(info, 255)))
        self._out.append((FrameKind.FAULT, self._fault_payload))
        self._out.append(self._heartbeat(DriveState.FAULT))

    # --- time ----------------------------------------------------------------------------------
    def integrate_to(self, t_ns: int) -> None:
        """Advance the physics to ``t_ns``, switching the current at every change due on the way.

        A change due exactly at ``t_ns`` is applied by the next call, so at a sample instant
        :attr:`CurrentPath.held_A` is the current that acted just before it.
        """
        if not self._physics_ok:
            self.time_ns = max(self.time_ns, t_ns)
            return
        try:
            t = self.time_ns
            path = self.path
            if t < t_ns and path.advance_held(self.plant, t, t_ns):  # one held current over the span
                self.time_ns = t_ns
            else:
                self._integrate_to(t_ns)
        except (OverflowError, ValueError, FloatingPointError):
            # the physics left the float range (a diverging or absurd plant): the position can no
            # longer be measured, as an encoder that lost track; the state is frozen from here
            self._physics_ok = False
            self.fault(FaultCode.ENCODER, 0, self.time_ns)
            self.time_ns = max(self.time_ns, t_ns)

    def _integrate_to(self, t_ns: int) -> None:
        path, plant = self.path, self.plant
        t = self.time_ns
        if t < t_ns:
            path.apply_due(t)
            if not path.pending:  # the common case: one held current over the whole span
                plant.advance(t, t_ns, path.held_A)
                self.time_ns = t_ns
                return
        while t < t_ns:
            path.apply_due(t)
            nxt = path.next_change_ns()
            end = t_ns if nxt is None or nxt > t_ns else nxt
            plant.advance(t, end, path.held_A)
            t = end
        self.time_ns = max(self.time_ns, t_ns)

    def period_boundary(self, commanded: bool) -> None:
        """Close one period at :attr:`time_ns`: watchdog (while ENABLED) and the 10 Hz heartbeat."""
        if self.faults is not None:
            self.faults.on_period(self, self.time_ns // self.period_ns)
        state = self.machine.state
        if state is DriveState.ENABLED:
            watchdog = self.watchdog
            if commanded:  # CommandWatchdog.period_elapsed(True), inline (the per-period path)
                watchdog.armed = True
                watchdog.missed = 0
            elif watchdog.period_elapsed(False):
                self.fault(FaultCode.WATCHDOG, watchdog.info, self.time_ns)
                state = self.machine.state
        if self.time_ns >= self._next_heartbeat_ns:
            if state is DriveState.FAULT:  # repeated, so a host started later learns it
                self._out.append((FrameKind.FAULT, self._fault_payload))
            self._out.append(self._heartbeat(state))
            while self._next_heartbeat_ns <= self.time_ns:
                self._next_heartbeat_ns += HEARTBEAT_PERIOD_NS

    def sample(self) -> tuple[bytes, GroundTruth | None]:
        """Latch the encoder at :attr:`time_ns`: the FEEDBACK payload and (if wanted) the truth."""
        machine = self.machine
        state = machine.state
        plant = self.plant
        try:
            counts = self.encoder.read(plant.position())
        except ValueError:  # not finite, or beyond any count (Encoder.read)
            self.fault(FaultCode.ENCODER, 0, self.time_ns)
            state, counts = machine.state, 0
        t = self.time_ns
        if self.faults is not None:
            counts = self.faults.counts(t // self.period_ns, counts)
        if state is DriveState.ENABLED:
            status = _ST_ENABLED_SATURATED if self.saturated else _ST_ENABLED
        elif state is DriveState.FAULT:
            status = _ST_FAULT_WATCHDOG if machine.fault_code is FaultCode.WATCHDOG else _ST_FAULT
        else:
            status = _ST_OFF
        n = self._samples
        seq = (n - self._seq_origin) % SEQ_MODULO
        self._samples = n + 1
        self.stats.samples += 1
        try:  # the codec's layout packed directly (per period); the codec names a bad value
            payload = _FEEDBACK_STRUCT.pack(counts, seq, status)
        except struct.error:
            payload = encode_feedback(FeedbackFrame(counts, seq, Status(status)))
        if self._pad:
            payload += _PADDING[len(payload) :]
        if not self.want_truth:
            return payload, None
        # GroundTruth(period_index, time_ns, state, w, i, drive state) by tuple.__new__: the
        # per-period path, without NamedTuple's Python-level __new__
        truth = _new_tuple(
            GroundTruth,
            (
                t // self.period_ns,
                t,
                plant.state,
                self.disturbance.value_A(t * 1e-9),
                self.path.held_A,
                state,
            ),
        )
        return payload, truth
