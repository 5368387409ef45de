"""Lockstep clock of a multi-axis drive: one period per valid COMMAND of *every* axis. No threads.

As :mod:`firmware_sim.lockstep`, for N nodes on one bus: :meth:`MultiAxisLockstepClock.service`
drains the frames pending on the drive's bus end and acts on each at the current simulated instant.

* CONTROL requests go to their axis (HEARTBEAT answer). Once the frames pending are read, if an
  axis entered ENABLED and the instant has no sample yet, every axis samples it (the FEEDBACKs of
  the instant; sequence 0 at t = 0 on the first enable).
* A valid COMMAND acts at this instant on its axis's input. When every axis has a valid command
  for the period, one period of the coupled plant is integrated and every axis's next FEEDBACK
  goes out (all of one period, in axis order).
* :meth:`advance_period` runs one period with the commands that did arrive (an axis without one
  holds its current and its watchdog counts a missed period).

``sim.loss_probability`` drops each FEEDBACK frame on its own (seeded).
"""

from __future__ import annotations

from collections.abc import Callable

import can

from dob_hil.config import Config
from dob_hil.link.protocol import DriveState
from firmware_sim.axes.core import AxesTruth, MultiAxisCore
from firmware_sim.behaviour import REFERENCE, DriveBehaviour
from firmware_sim.core import FrameResult
from firmware_sim.impairments import FeedbackImpairment


class MultiAxisLockstepClock:
    def __init__(
        self,
        bus: can.BusABC,
        config: Config,
        truth_sink: Callable[[AxesTruth], None] | None = None,
        behaviour: DriveBehaviour = REFERENCE,
    ) -> None:
        self.bus = bus
        self.core = MultiAxisCore(config, accept_window=1, want_truth=truth_sink is not None,
                                  behaviour=behaviour)  # fmt: skip
        self.truth_sink = truth_sink
        sim = config.sim
        self.impairment = FeedbackImpairment(0.0, 0.0, sim.loss_probability, sim.seed)
        self._sampled_period = -1  # the period index of the last sample instant

    def service(self) -> int:
        """Act on the frames pending (non-blocking) until every axis's COMMAND advanced the period."""
        recv = self.bus.recv
        core = self.core
        rx_ids = core.rx_ids
        n = 0
        entered_enabled = False
        while True:
            try:
                msg = recv(0.0)
            except can.CanError:
                core.stats.rx_errors += 1
                n += 1
                continue
            if msg is None:
                break
            n += 1
            aid = msg.arbitration_id
            if aid not in rx_ids or msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
                core.stats.frames_ignored += 1
                continue
            axis = core.axis_of(aid)
            assert axis is not None
            before = core.axes[axis].state
            result = core.on_frame(aid, msg.data, core.time_ns)
            if result is FrameResult.COMMAND and core.all_commanded:
                self._run_period()
                return n
            if result is FrameResult.CONTROL and before is not DriveState.ENABLED:
                entered_enabled = entered_enabled or core.axes[axis].state is DriveState.ENABLED
            self._send_outgoing()
        if entered_enabled and self._sampled_period != core.period_index:
            self._send_sample()
        return n

    def advance_period(self) -> None:
        """One period with the commands that arrived, then every axis's next FEEDBACK."""
        self._run_period()

    def _run_period(self) -> None:
        core = self.core
        core.integrate_to(core.time_ns + core.period_ns)
        core.period_boundary()
        self._send_outgoing()
        self._send_sample()

    def _send_sample(self) -> None:
        core = self.core
        frames, truth = core.sample()
        self._sampled_period = core.period_index
        for aid, payload in frames:
            if self.impairment.lost():
                core.stats.feedback_lost += 1
            elif self._send(aid, payload):
                core.stats.feedback_sent += 1
        if truth is not None and self.truth_sink is not None:
            self.truth_sink(truth)

    def _send_outgoing(self) -> None:
        for aid, payload in self.core.take_outgoing():
            self._send(aid, payload)

    def _send(self, arbitration_id: int, payload: bytes) -> bool:
        if self.core.silent:
            self.core.stats.frames_suppressed += 1
            return False
        self.bus.send(can.Message(arbitration_id=arbitration_id, data=payload, is_extended_id=False))
        return True
