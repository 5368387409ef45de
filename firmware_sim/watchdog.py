"""Command watchdog, armed by the first valid command after enable (PROTOCOL.md "Watchdog").

Once armed, the ``periods``-th consecutive period without a valid command trips it (info: the
periods missed). Before the first command it counts against ``arm_periods`` instead (the host's
start-up time after the enable handshake; at least twice ``periods``); running out trips it with
info 0.
"""

from __future__ import annotations


class CommandWatchdog:
    def __init__(self, periods: int, arm_periods: int | None = None) -> None:
        if periods < 1:
            raise ValueError(f"watchdog periods must be >= 1, got {periods}")
        self.periods = periods
        self.arm_periods = max(2 * periods, arm_periods or 0)
        self.armed = False
        self.missed = 0  # consecutive periods without a valid command

    def reset(self) -> None:
        """On entering ENABLED: disarmed until the first valid command."""
        self.armed = False
        self.missed = 0

    @property
    def info(self) -> int:
        """The FAULT info of a trip: periods missed once armed, 0 for no first command (max 255)."""
        return min(self.missed, 255) if self.armed else 0

    def period_elapsed(self, commanded: bool) -> bool:
        """Account one period; True when it trips (see the module docstring)."""
        if commanded:
            self.armed = True
            self.missed = 0
            return False
        self.missed += 1
        return self.missed >= (self.periods if self.armed else self.arm_periods)
