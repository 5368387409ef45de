"""``SimulatedDrive``: the simulated servo drive on a python-can bus, with either clock.

It behaves like drive firmware and talks only through the bus (the native protocol of
:mod:`dob_hil.link.protocol`); the true plant state leaves only through ``truth_sink``.

Lockstep (deterministic, as fast as the CPU allows)::

    drive = SimulatedDrive(bus, config)               # clock="lockstep"
    ... host sends CONTROL enable ...
    drive.service()        # acts on every pending frame: answers with HEARTBEAT + FEEDBACK seq 0
    ... host reads feedback, sends COMMAND answering it ...
    drive.service()        # integrates one period, sends FEEDBACK seq 1

Real time (own timer and receive threads)::

    with SimulatedDrive(bus, config, clock="realtime") as drive:
        ...                # FEEDBACK every Ts; drive.check() re-raises a thread's exception

The drive does not own the bus: :meth:`close` stops the drive, the caller shuts the bus down.
"""

from __future__ import annotations

from typing import Protocol, TypeVar

import can

from dob_hil.config import Config
from dob_hil.link.protocol import DriveState
from firmware_sim.behaviour import REFERENCE, DriveBehaviour
from firmware_sim.clocked import ClockedDrive, ClockKind, CoreReadout, LockstepClockLike, RealtimeClockLike
from firmware_sim.core import DriveStats, TruthSink
from firmware_sim.lockstep import LockstepClock
from firmware_sim.realtime import RealtimeClock


class _LockstepReadout(LockstepClockLike, Protocol):
    @property
    def core(self) -> CoreReadout: ...


class _RealtimeReadout(RealtimeClockLike, Protocol):
    def snapshot(self) -> tuple[DriveState, int, tuple[float, ...], int, DriveStats]: ...


LR = TypeVar("LR", bound=_LockstepReadout)
RR = TypeVar("RR", bound=_RealtimeReadout)


class SnapshotDrive(ClockedDrive[LR, RR]):
    """The read-outs of a simulated drive whose clocks keep a firmware core (lockstep: read in
    this thread; real time: one consistent snapshot under the clock's lock)."""

    # --- read-out ------------------------------------------------------------------------------
    @property
    def state(self) -> DriveState:
        if self._realtime is not None:
            return self._realtime.snapshot()[0]
        assert self._lockstep is not None
        return self._lockstep.core.state

    @property
    def enabled(self) -> bool:
        """The power stage is on (state ENABLED)."""
        return self.state is DriveState.ENABLED

    @property
    def period_index(self) -> int:
        """Index of the sample instant the physics has reached (``time_ns // period_ns``)."""
        if self._realtime is not None:
            return self._realtime.snapshot()[1]
        assert self._lockstep is not None
        return self._lockstep.core.period_index

    @property
    def true_state(self) -> tuple[float, ...]:
        """The true plant state at :attr:`time_ns` (for tests and analysis; never on the bus)."""
        if self._realtime is not None:
            return self._realtime.snapshot()[2]
        assert self._lockstep is not None
        return self._lockstep.core.plant.state

    @property
    def time_ns(self) -> int:
        """Simulated time the physics has been integrated to."""
        if self._realtime is not None:
            return self._realtime.snapshot()[3]
        assert self._lockstep is not None
        return self._lockstep.core.time_ns

    @property
    def stats(self) -> DriveStats:
        """A copy of the drive's counters."""
        if self._realtime is not None:
            return self._realtime.snapshot()[4]
        assert self._lockstep is not None
        return DriveStats(**vars(self._lockstep.core.stats))


class SimulatedDrive(SnapshotDrive[LockstepClock, RealtimeClock]):
    def __init__(
        self,
        bus: can.BusABC,
        config: Config,
        *,
        clock: ClockKind = "lockstep",
        truth_sink: TruthSink | None = None,
        spin_ns: int = 0,
        behaviour: DriveBehaviour = REFERENCE,
    ) -> None:
        """``spin_ns`` (real time only): busy-wait (yielding) this long before each deadline.
        ``behaviour``: a variant PROTOCOL.md permits, or a deliberate violation
        (:mod:`firmware_sim.behaviour`); default the reference drive."""
        self.config = config
        self.clock: ClockKind = clock
        if clock == "lockstep":
            self._lockstep = LockstepClock(bus, config, truth_sink, behaviour)
        elif clock == "realtime":
            self._realtime = RealtimeClock(bus, config, truth_sink, spin_ns=spin_ns, behaviour=behaviour)
        else:
            raise ValueError(f"clock must be 'lockstep' or 'realtime', got {clock!r}")
        self._closed = False
