"""Real-time clock of a multi-axis drive: :class:`firmware_sim.realtime.ThreadedDriveClock`'s
threads around a :class:`~firmware_sim.axes.core.MultiAxisCore`.

At each deadline the coupled plant is integrated to the instant with every axis's current, every
axis closes its period (its watchdog counts its own commands) and latches its encoder, and the
FEEDBACKs of all axes go out (each dropped on its own with ``sim.loss_probability``; latency and
jitter delay the period's frames together). A received COMMAND or CONTROL acts on its axis at its
arrival instant.
"""

from __future__ import annotations

from typing import Any

import can

from dob_hil.config import Config
from dob_hil.link.protocol import DriveState
from firmware_sim.axes.core import MultiAxisCore
from firmware_sim.behaviour import REFERENCE, DriveBehaviour
from firmware_sim.core import DriveStats
from firmware_sim.realtime import Outgoing, ThreadedDriveClock


class MultiAxisRealtimeClock(ThreadedDriveClock):
    def __init__(
        self,
        bus: can.BusABC,
        config: Config,
        truth_sink: Any = None,
        *,
        spin_ns: int = 0,
        behaviour: DriveBehaviour = REFERENCE,
    ) -> None:
        super().__init__(bus, config, truth_sink, spin_ns=spin_ns)
        window = min(config.drive.watchdog_periods, 64)
        self.core: MultiAxisCore = MultiAxisCore(
            config, accept_window=max(window, 2), want_truth=truth_sink is not None, behaviour=behaviour
        )
        self.core.plant.precompute_splits()  # commands act at their arrival, inside a cell
        self._stats = self.core.stats
        self._rx_ids = self.core.rx_ids
        self._feedback_ids = frozenset(self.core.feedback_ids)

    def axis_snapshot(self) -> tuple[tuple[DriveState, ...], list[DriveStats], tuple[float, ...]]:
        """Each axis's state, counters and current (once the changes commanded are due)."""
        with self._lock:
            c = self.core
            return c.states, c.axis_stats(), tuple(p.final_A for p in c.paths)

    def _silent(self) -> bool:
        return self.core.silent

    def _tick(self, k: int) -> tuple[Outgoing, Outgoing, Any]:
        core = self.core
        core.integrate_to(k * self.period_ns)
        if k > 0:
            core.period_boundary()
        frames = core.take_outgoing()
        feedback, truth = core.sample()
        kept = []
        for frame in feedback:
            if self.impairment.lost():
                core.stats.feedback_lost += 1
            else:
                kept.append(frame)
        return frames, kept, truth

    def _on_rx(self, arbitration_id: int, data: bytes | bytearray, t_ns: int) -> Outgoing:
        core = self.core
        core.on_frame(arbitration_id, data, max(t_ns, core.time_ns))
        return core.take_outgoing()
