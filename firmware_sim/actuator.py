"""The current path: the current the power stage applies now, and commanded changes still in flight.

With ``plant.input_delay_samples = d`` a current commanded at ``t`` acts from ``t + d Ts``. A
change takes effect exactly at its instant; :meth:`cut` (disable, fault) zeroes the current at
once and drops every change due later, since a disabled power stage applies nothing.
"""

from __future__ import annotations

import bisect
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from firmware_sim.plant import PlantModel


class CurrentPath:
    def __init__(self) -> None:
        self.held_A = 0.0
        self._times_ns: list[int] = []
        self._currents_A: list[float] = []

    def schedule(self, t_ns: int, current_A: float) -> None:
        """``current_A`` acts from ``t_ns`` on (after any change already due at the same instant)."""
        times = self._times_ns
        if not times or t_ns >= times[-1]:
            times.append(t_ns)
            self._currents_A.append(current_A)
            return
        i = bisect.bisect_right(times, t_ns)
        times.insert(i, t_ns)
        self._currents_A.insert(i, current_A)

    def cut(self, t_ns: int) -> None:
        """Zero current from ``t_ns`` on; changes due after ``t_ns`` are dropped."""
        i = bisect.bisect_right(self._times_ns, t_ns)
        del self._times_ns[i:], self._currents_A[i:]
        self.schedule(t_ns, 0.0)

    def next_change_ns(self) -> int | None:
        return self._times_ns[0] if self._times_ns else None

    def apply_due(self, t_ns: int) -> None:
        """Make every change due at or before ``t_ns`` the held current."""
        times = self._times_ns
        n = 0
        while n < len(times) and times[n] <= t_ns:
            n += 1
        if n:
            self.held_A = self._currents_A[n - 1]
            del times[:n], self._currents_A[:n]

    def advance_held(self, plant: PlantModel, t0_ns: int, t1_ns: int) -> bool:
        """:meth:`apply_due` at ``t0_ns``, then, if no change is pending after it, ``plant``
        advanced from ``t0_ns`` to ``t1_ns`` with the held current (its 2-state path where it
        applies, else :meth:`PlantModel.advance`, bit for bit the same) and True. False with the
        plant untouched when a change is pending: the caller integrates change by change.

        One call for the common case of the per-period paths: the native core's
        :meth:`~firmware_sim.core.DriveCore.integrate_to`, the CiA 402 fused SYNC, the ODrive
        period."""
        times = self._times_ns
        if times and times[0] <= t0_ns:
            if len(times) == 1:  # the one change the last period scheduled (apply_due, inline)
                self.held_A = self._currents_A.pop()
                times.pop()
            else:
                self.apply_due(t0_ns)
        if times:
            return False
        held_A = self.held_A
        if not plant.advance_2state(t0_ns, t1_ns, held_A):
            plant.advance(t0_ns, t1_ns, held_A)
        return True

    @property
    def final_A(self) -> float:
        """The current held once every change already scheduled is due."""
        return self._currents_A[-1] if self._currents_A else self.held_A

    @property
    def pending(self) -> int:
        return len(self._times_ns)
