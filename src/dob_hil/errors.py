"""Error types. Every error a user can cause names what was wrong; the CLI prints it as one line."""

from __future__ import annotations


class DobHilError(Exception):
    """Base class of every error dob_hil raises on purpose (bad input, unstable design, ...)."""


class ConfigError(DobHilError):
    """A configuration value is missing or wrong. ``field`` is its dotted path, e.g. ``plant.A``."""

    def __init__(self, field: str, problem: str) -> None:
        super().__init__(f"{field}: {problem}")
        self.field = field
        self.problem = problem


class DesignError(DobHilError):
    """A controller design that must not be run (unstable loop, wrong shapes, no DARE solution)."""


class ProtocolError(DobHilError):
    """A value that does not fit a protocol signal, or a malformed frame."""


class LogReadError(DobHilError):
    """An MCAP log that cannot be read (missing, not MCAP, corrupted beyond its first chunk)."""


class LogWriteError(DobHilError):
    """The log cannot be written: bad path, writer process failed (disk full), bad record value."""


class DriveFault(DobHilError):
    """The drive reported a fault, stopped answering, or the run had to stop for safety."""
