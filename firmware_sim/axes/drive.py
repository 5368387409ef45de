"""``MultiAxisDrive``: N simulated drive nodes on one python-can bus sharing one coupled plant.

The multi-axis counterpart of :class:`firmware_sim.drive.SimulatedDrive` (same clocks, same
read-outs; the true state is the coupled plant's), for a square plant with N > 1 inputs.
:func:`make_simulated_drive` picks it or the single-axis drive by the plant's inputs.
"""

from __future__ import annotations

from typing import Any

import can

from dob_hil.config import Config
from dob_hil.link.protocol import DriveState
from firmware_sim.axes.lockstep import MultiAxisLockstepClock
from firmware_sim.axes.realtime import MultiAxisRealtimeClock
from firmware_sim.behaviour import REFERENCE, DriveBehaviour
from firmware_sim.clocked import ClockKind
from firmware_sim.core import DriveStats
from firmware_sim.drive import SimulatedDrive, SnapshotDrive


class MultiAxisDrive(SnapshotDrive[MultiAxisLockstepClock, MultiAxisRealtimeClock]):
    def __init__(
        self,
        bus: can.BusABC,
        config: Config,
        *,
        clock: ClockKind = "lockstep",
        truth_sink: Any = None,
        spin_ns: int = 0,
        behaviour: DriveBehaviour = REFERENCE,
    ) -> None:
        """As :class:`~firmware_sim.drive.SimulatedDrive`; ``truth_sink`` receives
        :class:`~firmware_sim.axes.core.AxesTruth` (per-input disturbance and current)."""
        self.config = config
        self.clock: ClockKind = clock
        if clock == "lockstep":
            self._lockstep = MultiAxisLockstepClock(bus, config, truth_sink, behaviour)
        elif clock == "realtime":
            self._realtime = MultiAxisRealtimeClock(bus, config, truth_sink, spin_ns=spin_ns,
                                                    behaviour=behaviour)  # fmt: skip
        else:
            raise ValueError(f"clock must be 'lockstep' or 'realtime', got {clock!r}")
        self._closed = False
        clock_obj = self._lockstep or self._realtime
        assert clock_obj is not None
        self.node_ids = clock_obj.core.node_ids

    @property
    def n_axes(self) -> int:
        return len(self.node_ids)

    # --- read-out ------------------------------------------------------------------------------
    @property
    def axis_states(self) -> tuple[DriveState, ...]:
        """The state of each axis."""
        if self._realtime is not None:
            return self._realtime.axis_snapshot()[0]
        assert self._lockstep is not None
        return self._lockstep.core.states

    @property
    def enabled(self) -> bool:
        """Any axis's power stage is on (the session stops until none is)."""
        return DriveState.ENABLED in self.axis_states

    @property
    def axis_stats(self) -> list[DriveStats]:
        """Each axis's firmware counters (commands accepted, stale, stops, ...)."""
        if self._realtime is not None:
            return self._realtime.axis_snapshot()[1]
        assert self._lockstep is not None
        return self._lockstep.core.axis_stats()

    @property
    def applied_currents_A(self) -> tuple[float, ...]:
        """The current each axis holds once the changes already commanded are due (for tests)."""
        if self._realtime is not None:
            return self._realtime.axis_snapshot()[2]
        assert self._lockstep is not None
        return tuple(p.final_A for p in self._lockstep.core.paths)


def make_simulated_drive(
    bus: can.BusABC,
    config: Config,
    *,
    clock: ClockKind = "lockstep",
    truth_sink: Any = None,
    spin_ns: int = 0,
    behaviour: DriveBehaviour = REFERENCE,
) -> SimulatedDrive | MultiAxisDrive:
    """The single-axis drive for a plant with one input, the multi-axis drive for N > 1 inputs."""
    if config.plant.n_inputs > 1:
        return MultiAxisDrive(bus, config, clock=clock, truth_sink=truth_sink, spin_ns=spin_ns,
                              behaviour=behaviour)  # fmt: skip
    return SimulatedDrive(bus, config, clock=clock, truth_sink=truth_sink, spin_ns=spin_ns,
                          behaviour=behaviour)  # fmt: skip
