"""The simulated ODrive's firmware logic, independent of any clock: frames in, frames out.

An ODrive axis as its CANSimple users see it (firmware 0.6.x frames, :mod:`dob_hil.link.odrive.codec`):

* Axis state machine: IDLE at power-up; Set_Axis_State CLOSED_LOOP_CONTROL enters closed loop
  when no axis error is active (otherwise the request is refused and the axis stays IDLE, as
  the firmware's disarm does); IDLE leaves it. Other requested states are acknowledged by
  staying where it is (this drive has no calibration to run).
* Set_Controller_Mode: closed loop applies Set_Input_Torque only in TORQUE_CONTROL with
  PASSTHROUGH input (any other mode: zero current, like a torque loop that is not configured).
* Set_Input_Torque (N m) acts from its arrival: current = torque / torque constant, clamped at
  ``drive.current_limit_A`` (the drive's current limit); ignored outside closed loop. Set while
  IDLE, it is held as the input the axis starts with.
* The watchdog (``axis.config.watchdog_timeout`` = ``drive.watchdog_periods`` periods): in
  closed loop, that many periods in a row without Set_Input_Torque set WATCHDOG_TIMER_EXPIRED
  and drop the axis to IDLE (zero current).
* Clear_Errors clears the axis errors (the axis stays IDLE; the host requests closed loop again).
* Heartbeat every ``heartbeat_msg_rate_ms``; Get_Encoder_Estimates every ``encoder_msg_rate_ms``
  (0: never) and on RTR, in every state: position in turns (``encoder_counts_per_unit / encoder_cpr``
  turns per plant unit) and velocity in turns/s (``C A x``, exact for a position output with
  ``C B = 0``), both float32, the position with the encoder's noise if configured.
* Injected faults (``[sim.faults]``) as in the native drive: ``fault_at_s`` sets DRV_FAULT (axis
  to IDLE), ``silent_at_s`` silences the transmitter, ``encoder_jump_at_s`` offsets the position
  by ``encoder_jump_counts`` encoder counts. A non-finite plant position sets MISSING_ESTIMATE.

The physics (plant, disturbances, current path) is firmware_sim's; the disturbances start when
the axis first enters closed loop (:class:`StartAtEnable`). ``plant.input_delay_samples``
is the design's model of the delay and is not added here: the torque acts when it arrives.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from dob_hil.config import Config
from dob_hil.errors import ProtocolError
from dob_hil.link.odrive import codec
from dob_hil.link.odrive.codec import AxisState, CmdId, ControlMode, InputMode, ODriveError
from dob_hil.link.odrive.options import odrive_options
from dob_hil.link.protocol import DriveState
from firmware_sim.actuator import CurrentPath
from firmware_sim.disturbance import Disturbance
from firmware_sim.faults import DriveFaults
from firmware_sim.plant import PlantModel, check_single_axis
from firmware_sim.truth import GroundTruth

_ESTIMATES = struct.Struct("<ff")
_F32_MAX = 3.4028234663852886e38

Outgoing = tuple[int, bytes]  # (arbitration id, payload)
TruthSink = Callable[[GroundTruth], None]


_CLOSED_LOOP = AxisState.CLOSED_LOOP_CONTROL  # (the closed_loop property, inline on the per-period path)


@dataclass
class OdriveStats:
    samples: int = 0  # encoder estimates taken
    feedback_sent: int = 0
    feedback_lost: int = 0
    rtr_answered: int = 0
    heartbeats_sent: int = 0
    commands_accepted: int = 0
    bad_frames: int = 0
    frames_ignored: int = 0
    saturations: int = 0
    overruns: int = 0
    send_failures: int = 0
    frames_suppressed: int = 0
    rx_errors: int = 0  # error frames received


class OdriveCore:
    def __init__(self, config: Config, *, want_truth: bool) -> None:
        check_single_axis(config.plant)
        drive, sim, plant = config.drive, config.sim, config.plant
        options = odrive_options(config, host_clocked=None)  # the simulated ODrive serves both clockings
        self.cyclic = options.encoder_msg_rate_ms > 0  # estimates every period; else only on RTR
        self.node_id = drive.node_id
        self.ids = {cmd: codec.arbitration_id(drive.node_id, cmd) for cmd in CmdId}
        self.estimates_id = self.ids[CmdId.GET_ENCODER_ESTIMATES]
        self.heartbeat_id = self.ids[CmdId.HEARTBEAT]
        self._handlers: dict[int, Callable[[bytes, int], None]] = {
            self.ids[CmdId.SET_AXIS_STATE]: self._on_set_axis_state,
            self.ids[CmdId.SET_CONTROLLER_MODE]: self._on_set_controller_mode,
            self.ids[CmdId.SET_INPUT_TORQUE]: self._on_set_input_torque,
            self.ids[CmdId.CLEAR_ERRORS]: self._on_clear_errors,
        }
        self.period_ns = plant.period_ns
        self.want_truth = want_truth
        self.kt = options.torque_constant_Nm_per_A
        self.current_limit_A = drive.current_limit_A
        self.turns_per_unit = drive.encoder_counts_per_unit / options.encoder_cpr
        self.cpr = options.encoder_cpr
        self.heartbeat_ns = options.heartbeat_msg_rate_ms * 1_000_000
        self.watchdog_periods = drive.watchdog_periods
        self.disturbance = StartAtEnable(Disturbance(sim.disturbances, plant.period_s / sim.substeps))
        self.plant = PlantModel(plant, sim.substeps, cast(Disturbance, self.disturbance), sim.initial_state)
        self.vel_row = [float(v) for v in (np.asarray(plant.C) @ np.asarray(plant.A))[0]]
        self.noise_std_counts = sim.noise_counts_std
        self.rng = np.random.default_rng([sim.seed, 0x0D])
        self.path = CurrentPath()
        self.stats = OdriveStats()
        self.axis_state = AxisState.IDLE
        self.axis_error = 0
        self.control_mode = ControlMode.VOLTAGE_CONTROL
        self.input_mode = InputMode.INACTIVE
        self.torque_passthrough = False  # Set_Input_Torque drives the current: TORQUE_CONTROL, PASSTHROUGH
        self.input_torque_Nm = 0.0
        self.time_ns = 0
        self.missed = 0  # watchdog: periods in a row in closed loop without a torque input
        self.fed = False  # a torque input arrived in the current period
        self.next_heartbeat_ns = self.heartbeat_ns
        self.out: list[Outgoing] = []
        self._heartbeat_key: tuple[int, AxisState] | None = None  # (axis error, state) last encoded
        self._heartbeat_payload = b""
        self.faults = DriveFaults.from_config(config)
        self.silent = False

    # --- read-out ------------------------------------------------------------------------------
    @property
    def period_index(self) -> int:
        return self.time_ns // self.period_ns

    @property
    def closed_loop(self) -> bool:
        return self.axis_state is AxisState.CLOSED_LOOP_CONTROL

    @property
    def drive_state(self) -> DriveState:
        """The state in the ground-truth log's terms."""
        if self.axis_error:
            return DriveState.FAULT
        return DriveState.ENABLED if self.axis_state is _CLOSED_LOOP else DriveState.DISABLED

    def take_outgoing(self) -> list[Outgoing]:
        out, self.out = self.out, []
        return out

    # --- frames --------------------------------------------------------------------------------
    def on_frame(self, arbitration_id: int, data: bytes | bytearray, remote: bool, t_ns: int) -> CmdId | None:
        """Act on a frame at ``t_ns`` (>= time_ns). Returns the command it was (None: not ours or bad).

        An RTR Get_Encoder_Estimates is returned as GET_ENCODER_ESTIMATES: the caller samples
        (:meth:`estimates`) at the instant it chooses, after integrating up to it.
        """
        if remote:
            if arbitration_id == self.estimates_id:
                return CmdId.GET_ENCODER_ESTIMATES
            self.stats.frames_ignored += 1
            return None
        handler = self._handlers.get(arbitration_id)
        if handler is None:
            self.stats.frames_ignored += 1
            return None
        try:
            handler(bytes(data), t_ns)
        except ProtocolError:
            self.stats.bad_frames += 1  # ODrive ignores a frame it cannot decode
            return None
        return CmdId(arbitration_id & codec.CMD_ID_MASK)

    def _on_set_axis_state(self, data: bytes, t_ns: int) -> None:
        requested = codec.decode_set_axis_state(data)
        if requested is AxisState.CLOSED_LOOP_CONTROL:
            if not self.axis_error and self.axis_state is not _CLOSED_LOOP:
                self.axis_state = AxisState.CLOSED_LOOP_CONTROL
                self.missed, self.fed = 0, False
                self.apply(t_ns)
                self.disturbance.start(t_ns)
                if self.faults is not None:
                    self.faults.on_enabled(self.period_index)
        elif requested is AxisState.IDLE:
            self._idle(t_ns)

    def _on_set_controller_mode(self, data: bytes, t_ns: int) -> None:
        self.control_mode, self.input_mode = codec.decode_set_controller_mode(data)
        self.torque_passthrough = (
            self.control_mode is ControlMode.TORQUE_CONTROL and self.input_mode is InputMode.PASSTHROUGH
        )
        if self.axis_state is _CLOSED_LOOP:
            self.apply(t_ns)

    def _on_set_input_torque(self, data: bytes, t_ns: int) -> None:
        torque = codec.decode_set_input_torque(data)
        if not math.isfinite(torque):
            raise ProtocolError("Set_Input_Torque: not finite")
        self.input_torque_Nm = torque
        self.stats.commands_accepted += 1
        if self.axis_state is _CLOSED_LOOP:
            self.fed = True
            self.apply(t_ns)

    def _on_clear_errors(self, data: bytes, t_ns: int) -> None:
        codec.decode_clear_errors(data)
        self.axis_error = 0

    def apply(self, t_ns: int) -> None:
        """The current the torque loop applies from ``t_ns`` (closed loop only)."""
        if not self.torque_passthrough:
            self.path.schedule(t_ns, 0.0)
            return
        current = self.input_torque_Nm / self.kt
        if abs(current) > self.current_limit_A:
            current = math.copysign(self.current_limit_A, current)
            self.stats.saturations += 1
        self.path.schedule(t_ns, current)

    def _idle(self, t_ns: int) -> None:
        if self.axis_state is _CLOSED_LOOP:
            self.path.cut(t_ns)
        self.axis_state = AxisState.IDLE

    def fault(self, code: object, info: int, t_ns: int) -> None:
        """An injected fault (:mod:`firmware_sim.faults`): DRV_FAULT, axis to IDLE."""
        self.set_error(ODriveError.DRV_FAULT, t_ns)

    def set_error(self, error: ODriveError, t_ns: int) -> None:
        self.axis_error |= int(error)
        self._idle(t_ns)

    # --- time ----------------------------------------------------------------------------------
    def integrate_to(self, t_ns: int) -> None:
        """Advance the physics to ``t_ns``, switching the current at every change due on the way."""
        path, plant = self.path, self.plant
        t = self.time_ns
        while t < t_ns:
            path.apply_due(t)
            nxt = path.next_change_ns()
            end = t_ns if nxt is None or nxt > t_ns else nxt
            plant.advance(t, end, path.held_A)
            t = end
        self.time_ns = max(self.time_ns, t_ns)

    def period_boundary(self) -> None:
        """Close one period at :attr:`time_ns`: injected faults, the watchdog, the heartbeat."""
        if self.faults is not None:
            self.faults.on_period(cast(Any, self), self.period_index)
            self.silent = self.faults.silent
        if self.axis_state is _CLOSED_LOOP:
            self.missed = 0 if self.fed else self.missed + 1
            self.fed = False
            if self.missed >= self.watchdog_periods:
                self.set_error(ODriveError.WATCHDOG_TIMER_EXPIRED, self.time_ns)
        self.heartbeat_if_due()

    def heartbeat_if_due(self) -> None:
        if self.time_ns >= self.next_heartbeat_ns:
            self.heartbeat_now()
            while self.next_heartbeat_ns <= self.time_ns:
                self.next_heartbeat_ns += self.heartbeat_ns

    def heartbeat_now(self) -> None:
        key = (self.axis_error, self.axis_state)
        if key != self._heartbeat_key:  # encoded again only when the axis error or state changed
            self._heartbeat_key = key
            self._heartbeat_payload = codec.encode_heartbeat(codec.Heartbeat(*key, 0, False))
        self.out.append((self.heartbeat_id, self._heartbeat_payload))
        self.stats.heartbeats_sent += 1

    def estimates(self) -> tuple[bytes, GroundTruth | None]:
        """Get_Encoder_Estimates at :attr:`time_ns` (and the truth, if wanted)."""
        x = self.plant.state
        pos_unit = self.plant.position()
        if not math.isfinite(pos_unit):
            self.set_error(ODriveError.MISSING_ESTIMATE, self.time_ns)
        offset_counts = 0 if self.faults is None else self.faults.counts(self.period_index, 0)
        noise_counts = self.rng.normal(0.0, self.noise_std_counts) if self.noise_std_counts > 0 else 0.0
        pos_turns = pos_unit * self.turns_per_unit + (offset_counts + noise_counts) / self.cpr
        vel_turns = sum(c * v for c, v in zip(self.vel_row, x, strict=True)) * self.turns_per_unit
        self.stats.samples += 1
        payload = self.pack_estimates(pos_turns, vel_turns)
        if not self.want_truth:
            return payload, None
        return payload, self.truth()

    @staticmethod
    def pack_estimates(pos_turns: float, vel_turns: float) -> bytes:
        """The Get_Encoder_Estimates payload: float32 (inf beyond their range; NaN if unpackable)."""
        try:
            return _ESTIMATES.pack(_clip_f32(pos_turns), _clip_f32(vel_turns))
        except (struct.error, OverflowError):
            return _ESTIMATES.pack(math.nan, math.nan)

    def truth(self) -> GroundTruth:
        """The ground truth at :attr:`time_ns` (never on the bus)."""
        t = self.time_ns
        state = (t // self.period_ns, t, self.plant.state, self.disturbance.value_A(t * 1e-9),
                 self.path.held_A, self.drive_state)  # fmt: skip
        return tuple.__new__(GroundTruth, state)  # without NamedTuple's Python-level __new__


class StartAtEnable:
    """firmware_sim's :class:`Disturbance`, with its time origin at the first closed-loop entry.

    A standalone drive runs from its process start; the configured disturbances (``start_s``
    relative to the run) begin when the host first enables the axis, as with the native drive's
    injected faults. Until then the plant is undisturbed. Duck-types ``Disturbance`` for
    :class:`~firmware_sim.plant.PlantModel` (which reads ``is_zero`` on every step).
    """

    def __init__(self, inner: Disturbance) -> None:
        self.inner = inner
        self.origin_s: float | None = None
        self.is_zero = True

    def start(self, t_ns: int) -> None:
        if self.origin_s is None:
            self.origin_s = t_ns * 1e-9
            self.is_zero = self.inner.is_zero

    def value_A(self, t_s: float) -> float:
        if self.origin_s is None or t_s < self.origin_s:
            return 0.0
        return self.inner.value_A(t_s - self.origin_s)

    def values_A(self, t_s: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        if self.origin_s is None:
            return np.zeros_like(t_s)
        return np.where(t_s >= self.origin_s, self.inner.values_A(t_s - self.origin_s), 0.0)


def _clip_f32(v: float) -> float:
    """float32 of ``v``: beyond the float32 range it is inf (as a float32 cast is on the drive)."""
    if math.isfinite(v) and abs(v) > _F32_MAX:
        return math.copysign(math.inf, v)
    return v
