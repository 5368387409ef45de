"""Lockstep clock: simulated time advances one period per valid command. No threads.

The host's loop calls :meth:`LockstepClock.service`, which drains every frame pending on the
drive's bus end and acts on each at the current simulated instant:

* CONTROL enable (from DISABLED): ENABLED, HEARTBEAT, and the FEEDBACK of the current instant
  (sequence 0 at t = 0 on the first enable).
* A valid COMMAND (answering the last feedback's sequence): the current acts from this sample
  instant (plus the input delay), held for Ts; one period is integrated; the next FEEDBACK
  (sequence + 1 mod 256) goes out. Valid commands advance time in every state, so a host keeps
  its loop running while the drive is disabled or faulted (it then applies zero current).
* :meth:`advance_period` runs one period with no command (the held current continues; the
  watchdog counts a missed period) and sends the next FEEDBACK.

Frame loss (``sim.loss_probability``, seeded) drops FEEDBACK frames here too; the sequence still
advances, so a host answering the sequence it expects keeps the exchange going. Latency and
jitter have no meaning without a wall clock and are ignored.
"""

from __future__ import annotations

import can

from dob_hil.config import Config
from dob_hil.link.message import data_frame
from dob_hil.link.protocol import COMMAND_SEQ_MODULO, SEQ_MODULO, DriveState, FaultCode, FrameKind
from firmware_sim.behaviour import REFERENCE, DriveBehaviour
from firmware_sim.core import (
    _COMMAND_DLC,
    _COMMAND_STRUCT,
    _FEEDBACK_STRUCT,
    _PADDING,
    _ST_ENABLED,
    _ST_ENABLED_SATURATED,
    DriveCore,
    FrameResult,
    TruthSink,
)
from firmware_sim.impairments import FeedbackImpairment
from firmware_sim.truth import GroundTruth

_COMMAND = FrameResult.COMMAND
_ENABLED = DriveState.ENABLED
_new_tuple = tuple.__new__


class LockstepClock:
    def __init__(
        self,
        bus: can.BusABC,
        config: Config,
        truth_sink: TruthSink | None = None,
        behaviour: DriveBehaviour = REFERENCE,
    ) -> None:
        self.bus = bus
        self.core = DriveCore(config, accept_window=1, want_truth=truth_sink is not None, behaviour=behaviour)
        self.truth_sink = truth_sink
        sim = config.sim
        self.impairment = FeedbackImpairment(0.0, 0.0, sim.loss_probability, sim.seed)
        self._feedback_id = FrameKind.FEEDBACK + self.core.node_id
        self._node_id = self.core.node_id
        self._lossy = sim.loss_probability > 0.0  # FeedbackImpairment.lost() draws only then
        # :meth:`_exchange` (the whole commanded period in one call) where it applies; False: the
        # general path for every period (tests compare the two)
        self.fused = True

    def service(self) -> int:
        """Act on the frames pending on the bus (non-blocking) until a COMMAND advances the period.

        Returns how many frames were read. Stopping after the command (rather than reading until
        the queue is empty) saves an empty receive per period; frames sent after the command are
        handled by the next call, as a real drive handles them in its next period.
        """
        recv = self.bus.recv
        core = self.core
        command_id, control_id = core.command_id, core.control_id
        n = 0
        while True:
            try:
                msg = recv(0.0)
            except can.CanError:  # a frame the bus could not deliver: counted, skipped
                core.stats.rx_errors += 1
                n += 1
                continue
            if msg is None:
                return n
            n += 1
            aid = msg.arbitration_id
            if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
                core.stats.frames_ignored += 1
                continue
            if aid == command_id:  # the per-period frame
                data = msg.data
                if len(data) == _COMMAND_DLC:  # DriveCore.on_frame's fast path, one call fewer
                    current_counts, tail = _COMMAND_STRUCT.unpack(data)
                    # enabling: the command, the period and the feedback in one call where it can
                    if tail & 0x80 and self.fused and self._exchange(current_counts, tail & 0x7F):
                        return n
                    # else the command and the period in one call where it can (as _run_period)
                    if tail & 0x80 and core.lockstep_period(current_counts, tail & 0x7F):
                        if core._out:
                            self._send_outgoing()
                        self._send_sample()
                        return n
                    result = core._on_command(current_counts, tail & 0x7F, bool(tail & 0x80), core.time_ns)
                else:
                    result = core.on_frame(aid, data, core.time_ns)
                if result is _COMMAND:
                    self._run_period(True)
                    return n
                if core._out:
                    self._send_outgoing()
                continue
            if aid != control_id:
                core.stats.frames_ignored += 1
                continue
            before = core.state
            result = core.on_frame(aid, msg.data, core.time_ns)
            if result is FrameResult.COMMAND:
                self._run_period(commanded=True)
                return n
            elif (
                result is FrameResult.CONTROL
                and before is not DriveState.ENABLED
                and core.state is DriveState.ENABLED
            ):
                self._send_outgoing()
                self._send_sample()
            else:
                self._send_outgoing()

    def _exchange(self, current_counts: int, seq7: int) -> bool:
        """The common commanded period in one call: an enabling COMMAND (``current_counts``,
        ``seq7``) acted on at :attr:`DriveCore.time_ns`, the period integrated, the FEEDBACK sent
        and the truth handed on, with the same effects (bit for bit) as
        :meth:`DriveCore.lockstep_period` + :meth:`_send_sample`, which spell out each step.

        Only where :meth:`DriveCore.lockstep_period` applies and moreover the plant has two states
        (the unrolled update) and the period starts on a cell boundary; otherwise False with
        nothing changed, and the caller takes those paths. A plant position the encoder cannot
        read hands the sample to :meth:`_send_sample` (the ENCODER fault)."""
        core = self.core
        last = core._samples - 1
        s = last - ((last - core._seq_origin - seq7) % COMMAND_SEQ_MODULO)
        plant = core.plant
        m2 = plant._m2
        t = core.time_ns
        period_ns = core.period_ns
        t_end = t + period_ns
        if (
            last < 0
            or last - s >= core.accept_window
            or s <= core._last_accepted
            or core.machine.state is not _ENABLED
            or core.faults is not None
            or core.delay_ns
            or core.path._times_ns  # a current change pending
            or t_end >= core._next_heartbeat_ns
            or not core._physics_ok
            or m2 is None
            or t % period_ns
        ):
            return False
        # --- the COMMAND (DriveCore.lockstep_period) ----------------------------------------
        core._last_accepted = s
        stats = core.stats
        stats.commands_accepted += 1
        limit = core._dac_limit  # Dac.convert
        code = limit if current_counts > limit else -limit if current_counts < -limit else current_counts
        u = code * core._dac_lsb_A
        core.saturated = saturated = code != current_counts
        if saturated:
            stats.saturations += 1
        core.path.held_A = u
        # --- the period's cells (PlantModel.advance, the unrolled 2-state update) ---------------
        disturbance = plant._disturbance
        try:
            if not plant.advance_2state(t, t_end, u):  # 2 states, t on a period boundary: applies
                plant.advance(t, t_end, u)
        except (OverflowError, ValueError, FloatingPointError):  # as DriveCore.lockstep_period
            core._physics_ok = False
            core.fault(FaultCode.ENCODER, 0, core.time_ns)
            core.time_ns = max(core.time_ns, t_end)
            self._finish_period(core)
            return True
        x0, x1 = plant._x
        core.time_ns = t_end
        watchdog = core.watchdog  # period_boundary(True): ENABLED, no heartbeat due
        watchdog.armed = True
        watchdog.missed = 0
        # --- the sample (DriveCore.sample) --------------------------------------------------------
        c = plant._c
        position = c[0] * x0 + c[1] * x1  # PlantModel.position
        try:
            counts = core.encoder.read(position)
        except ValueError:  # not finite, or beyond any count: the encoder faults (DriveCore.sample)
            self._finish_period(core)
            return True
        n = core._samples
        core._samples = n + 1
        stats.samples += 1
        payload = _FEEDBACK_STRUCT.pack(
            counts, (n - core._seq_origin) % SEQ_MODULO, _ST_ENABLED_SATURATED if saturated else _ST_ENABLED
        )
        if core._pad:
            payload += _PADDING[len(payload) :]
        # --- sent, lost or suppressed (_send_sample) ------------------------------------------------
        if self._lossy and self.impairment.lost():
            stats.feedback_lost += 1
        elif core.silent:
            stats.frames_suppressed += 1
        else:
            self.bus.send(data_frame(0.0, self._feedback_id, payload))
            stats.feedback_sent += 1
        sink = self.truth_sink
        if sink is not None and core.want_truth:
            sink(
                _new_tuple(
                    GroundTruth,
                    (t_end // period_ns, t_end, (x0, x1), disturbance.value_A(t_end * 1e-9), u, _ENABLED),
                )
            )
        return True

    def _finish_period(self, core: DriveCore) -> None:
        """:meth:`_exchange` after a fault on the way: the rest of the period as the general path."""
        if core.machine.state is DriveState.ENABLED:
            core.watchdog.armed = True
            core.watchdog.missed = 0
        if core._out:
            self._send_outgoing()
        self._send_sample()

    def advance_period(self) -> None:
        """One period without a command, then the next FEEDBACK."""
        self._run_period(commanded=False)

    def _run_period(self, commanded: bool) -> None:
        core = self.core
        core.integrate_to(core.time_ns + core.period_ns)
        core.period_boundary(commanded)
        if core._out:  # FAULT / HEARTBEAT frames of this period (rarely any)
            self._send_outgoing()
        self._send_sample()

    def _send_sample(self) -> None:
        core = self.core
        payload, truth = core.sample()
        if self._lossy and self.impairment.lost():
            core.stats.feedback_lost += 1
        elif core.silent:
            core.stats.frames_suppressed += 1
        else:
            self.bus.send(data_frame(0.0, self._feedback_id, payload))
            core.stats.feedback_sent += 1
        if truth is not None and self.truth_sink is not None:
            self.truth_sink(truth)

    def _send_outgoing(self) -> None:
        for kind, payload in self.core.take_outgoing():
            self._send(kind + self._node_id, payload)

    def _send(self, arbitration_id: int, payload: bytes) -> bool:
        """Send one frame; False if the drive is silent (an injected fault) and nothing went out."""
        if self.core.silent:
            self.core.stats.frames_suppressed += 1
            return False
        self.bus.send(can.Message(arbitration_id=arbitration_id, data=payload, is_extended_id=False))
        return True
