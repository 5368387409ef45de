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
from dob_hil.link.protocol import DriveState, FrameKind
from firmware_sim.behaviour import REFERENCE, DriveBehaviour
from firmware_sim.core import _COMMAND_DLC, _COMMAND_STRUCT, DriveCore, FrameResult, TruthSink
from firmware_sim.impairments import FeedbackImpairment

_COMMAND = FrameResult.COMMAND


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
                    # enabling: the command and the period in one call where it can (as _run_period)
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
            self.bus.send(can.Message(arbitration_id=self._feedback_id, data=payload, is_extended_id=False))
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
