"""``SimulatedOdrive``: the simulated ODrive on a python-can bus, lockstep or real time.

It follows the :class:`~dob_hil.profiles.base.SimulatedCounterpart` protocol, so the session
drives it like the native simulated drive. The drive does not own the bus.
"""

from __future__ import annotations

from collections.abc import Callable

import can

from dob_hil.config import Config
from dob_hil.link.odrive.codec import AxisState
from firmware_sim.clocked import ClockedDrive, ClockKind
from firmware_sim.odrive.clocks import OdriveLockstep, OdriveRealtime
from firmware_sim.odrive.core import OdriveCore, OdriveStats, TruthSink


class SimulatedOdrive(ClockedDrive[OdriveLockstep, OdriveRealtime]):
    def __init__(
        self,
        bus: can.BusABC,
        config: Config,
        *,
        clock: ClockKind = "lockstep",
        truth_sink: TruthSink | None = None,
        spin_ns: int = 0,
    ) -> None:
        self.config = config
        self.clock: ClockKind = clock
        self._core: OdriveCore | None = None  # lockstep: the clock's core (cheap per-period reads)
        if clock == "lockstep":
            self._lockstep = OdriveLockstep(bus, config, truth_sink)
            self._core = self._lockstep.core
        elif clock == "realtime":
            self._realtime = OdriveRealtime(bus, config, truth_sink, spin_ns=spin_ns)
        else:
            raise ValueError(f"clock must be 'lockstep' or 'realtime', got {clock!r}")
        self._closed = False

    # --- read-out ------------------------------------------------------------------------------
    @property
    def enabled(self) -> bool:
        """The axis is in CLOSED_LOOP_CONTROL (its power stage applies current)."""
        if self._realtime is not None:
            return self._realtime.snapshot()[0]
        assert self._lockstep is not None
        return self._lockstep.core.closed_loop

    @property
    def axis_state(self) -> AxisState:
        return AxisState.CLOSED_LOOP_CONTROL if self.enabled else AxisState.IDLE

    state = axis_state  # what the standalone drive reports on stopping

    @property
    def axis_error(self) -> int:
        core = self._realtime.core if self._realtime is not None else self._need_lockstep("axis_error").core
        return core.axis_error

    @property
    def period_index(self) -> int:
        core = self._core  # read by the lockstep loop every period: no property chain
        if core is not None:
            return core.time_ns // core.period_ns
        assert self._realtime is not None
        return self._realtime.snapshot()[1]

    @property
    def true_state(self) -> tuple[float, ...]:
        if self._realtime is not None:
            return self._realtime.snapshot()[2]
        assert self._lockstep is not None
        return self._lockstep.core.plant.state

    def lockstep_period_index(self) -> Callable[[], int]:
        """Lockstep: a cheap reader of :attr:`period_index` (the host-clocked runner reads it every
        sample; no property chain)."""
        core = self._need_lockstep("lockstep_period_index").core
        period_ns = core.period_ns
        return lambda: core.time_ns // period_ns

    @property
    def time_ns(self) -> int:
        if self._realtime is not None:
            return self._realtime.snapshot()[3]
        assert self._lockstep is not None
        return self._lockstep.core.time_ns

    @property
    def stats(self) -> OdriveStats:
        if self._realtime is not None:
            return self._realtime.snapshot()[4]
        assert self._lockstep is not None
        return OdriveStats(**vars(self._lockstep.core.stats))
