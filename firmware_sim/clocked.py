"""The part every simulated drive shares: one of two clocks, and the calls that go to it.

A profile's simulated drive (native, CiA 402, ODrive) runs its firmware on a lockstep clock (no
threads: the host's loop calls :meth:`ClockedDrive.service` and :meth:`ClockedDrive.advance_period`)
or on a real-time clock (its own threads: :meth:`ClockedDrive.start`, :meth:`ClockedDrive.stop`,
:meth:`ClockedDrive.check`). The subclass builds the clock it was asked for into ``_lockstep`` or
``_realtime``; its read-outs stay its own.
"""

from __future__ import annotations

import contextlib
from types import TracebackType
from typing import TYPE_CHECKING, Any, Generic, Literal, Protocol, TypeVar

if TYPE_CHECKING:
    from dob_hil.link.protocol import DriveState
    from firmware_sim.core import DriveStats
    from firmware_sim.plant import PlantModel

ClockKind = Literal["lockstep", "realtime"]


class CoreReadout(Protocol):
    """What read-outs take of a simulated drive's firmware core (firmware_sim.core.DriveCore,
    firmware_sim.axes.core.MultiAxisCore)."""

    time_ns: int
    stats: DriveStats

    @property
    def state(self) -> DriveState: ...

    @property
    def period_index(self) -> int: ...

    @property
    def plant(self) -> PlantModel: ...


class LockstepClockLike(Protocol):
    def service(self) -> int: ...

    def advance_period(self) -> None: ...


class RealtimeClockLike(Protocol):
    def start(self) -> None: ...

    def stop(self) -> None: ...

    def check(self) -> None: ...

    @property
    def running(self) -> bool: ...


L = TypeVar("L", bound=LockstepClockLike)
R = TypeVar("R", bound=RealtimeClockLike)
D = TypeVar("D", bound="ClockedDrive")  # type: ignore[type-arg]


class ClockedDrive(Generic[L, R]):
    """A simulated drive on a lockstep clock ``L`` or a real-time clock ``R`` (module docstring)."""

    _lockstep_clock: L | None = None
    _realtime: R | None = None
    _closed: bool = False

    @property
    def _lockstep(self) -> L | None:
        return self._lockstep_clock

    @_lockstep.setter
    def _lockstep(self, clock: L | None) -> None:
        """Set by the subclass; binds :meth:`service` and :meth:`advance_period` straight to the
        clock's (one call fewer each on the lockstep loop's per-period path)."""
        self._lockstep_clock = clock
        if clock is not None:
            vars(self).update(service=clock.service, advance_period=clock.advance_period)

    def lockstep_time_source(self) -> Any:
        """Lockstep: the object whose ``time_ns`` attribute is the simulated time, read by the
        session's frame stamper for every frame: the clock's ``core`` (a plain attribute), else
        the drive itself (its :attr:`time_ns` property)."""
        core = getattr(self._need_lockstep("lockstep_time_source"), "core", None)
        return core if core is not None and hasattr(core, "time_ns") else self

    # --- lockstep ------------------------------------------------------------------------------
    def service(self) -> int:
        """Lockstep: act on the frames pending on the bus (never blocks); returns how many were read."""
        return self._need_lockstep("service").service()

    def advance_period(self) -> None:
        """Lockstep: one period passes without the frame that normally advances it."""
        self._need_lockstep("advance_period").advance_period()

    def _need_lockstep(self, what: str) -> L:
        if self._lockstep is None:
            raise RuntimeError(f"{what}() is for the lockstep clock; this drive runs in real time")
        return self._lockstep

    # --- real time -----------------------------------------------------------------------------
    def start(self) -> None:
        """Real time: start the drive's threads. Nothing in lockstep."""
        if self._realtime is not None:
            self._realtime.start()

    def stop(self) -> None:
        """Real time: stop the threads; re-raise an exception one of them hit. Safe to call twice."""
        if self._realtime is not None:
            self._realtime.stop()

    def check(self) -> None:
        """Real time: re-raise the exception a drive thread stopped on, if any."""
        if self._realtime is not None:
            self._realtime.check()

    def close(self) -> None:
        """Stop the drive (safe to call twice). The bus stays open: it belongs to the caller."""
        if self._closed:
            return
        self._closed = True
        self.stop()

    def __enter__(self: D) -> D:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
            return
        with contextlib.suppress(Exception):
            self.close()  # the exception already propagating is the one to see

    @property
    def running(self) -> bool:
        """Real time: the threads are running (started, not stopped, no error). Lockstep: False."""
        return self._realtime is not None and self._realtime.running
