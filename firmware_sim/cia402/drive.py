"""``SimulatedCia402Drive``: the simulated CiA 402 drive on a python-can bus, with either clock.

Lockstep (deterministic; the host's SYNC advances time)::

    drive = SimulatedCia402Drive(bus, config)        # boot-up frame sent now
    ... host: SDO configuration (call drive.service() meanwhile), NMT start, enable ...
    ... host sends SYNC ...
    drive.service()        # integrates one period, samples, sends the TPDOs

Real time (its own receive thread; the SYNC arrivals are its clock)::

    with SimulatedCia402Drive(bus, config, clock="realtime") as drive:
        ...                # drive.check() re-raises a thread's exception

The drive does not own the bus: :meth:`close` stops the drive, the caller shuts the bus down.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import can

from dob_hil.config import Config
from firmware_sim.cia402.core import Cia402Core, Cia402Stats, TruthSink
from firmware_sim.cia402.lockstep import Cia402Lockstep
from firmware_sim.cia402.power import PowerState
from firmware_sim.cia402.realtime import Cia402Realtime
from firmware_sim.clocked import ClockedDrive, ClockKind


class SimulatedCia402Drive(ClockedDrive[Cia402Lockstep, Cia402Realtime]):
    def __init__(
        self,
        bus: can.BusABC,
        config: Config,
        *,
        clock: ClockKind = "lockstep",
        truth_sink: TruthSink | None = None,
        fast_path: bool = True,
    ) -> None:
        """``fast_path=False``: the lockstep clock takes the general path for every frame (tests
        compare it with the fused period of :mod:`firmware_sim.cia402.fast`)."""
        self.config = config
        self.clock: ClockKind = clock
        if clock == "lockstep":
            self._lockstep = Cia402Lockstep(bus, config, truth_sink, fast_path=fast_path)
            self._core, self._lock = self._lockstep.core, self._lockstep.lock
        elif clock == "realtime":
            self._realtime = Cia402Realtime(bus, config, truth_sink)
            self._core, self._lock = self._realtime.core, self._realtime.lock
        else:
            raise ValueError(f"clock must be 'lockstep' or 'realtime', got {clock!r}")
        self._closed = False

    # --- read-out ------------------------------------------------------------------------------
    @property
    def core(self) -> Cia402Core:
        """The firmware (tests; in real time, read it under :attr:`lock` or use the properties)."""
        return self._core

    @property
    def state(self) -> PowerState:
        with self._lock:
            return self._core.power.state

    @property
    def nmt_state(self) -> str:
        with self._lock:
            return self._core.node.nmt.state

    @property
    def enabled(self) -> bool:
        """OPERATION ENABLED: the drive applies the target torque."""
        return self.state is PowerState.OPERATION_ENABLED

    @property
    def period_index(self) -> int:
        with self._lock:
            return self._core.period_index

    def lockstep_period_index(self) -> Callable[[], int]:
        """Lockstep: a cheap reader of :attr:`period_index` (no property, no lock: the lockstep
        runner calls it every sample, in the only thread that services the drive then)."""
        return functools.partial(getattr, self._need_lockstep("lockstep_period_index").core, "period_index")

    @property
    def time_ns(self) -> int:
        with self._lock:
            return self._core.time_ns

    @property
    def true_state(self) -> tuple[float, ...]:
        with self._lock:
            return self._core.plant.state

    @property
    def error_code(self) -> int:
        with self._lock:
            return self._core.error_code

    @property
    def stats(self) -> Cia402Stats:
        with self._lock:
            return dataclasses.replace(self._core.stats)
