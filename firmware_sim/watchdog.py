"""Command watchdog: trips after ``periods`` consecutive periods without a valid command."""

from __future__ import annotations


class CommandWatchdog:
    def __init__(self, periods: int) -> None:
        if periods < 1:
            raise ValueError(f"watchdog periods must be >= 1, got {periods}")
        self.periods = periods
        self.missed = 0  # consecutive periods without a valid command

    def reset(self) -> None:
        self.missed = 0

    def period_elapsed(self, commanded: bool) -> bool:
        """Account one period; True when this period is the ``periods``-th in a row without a command."""
        if commanded:
            self.missed = 0
            return False
        self.missed += 1
        return self.missed >= self.periods
