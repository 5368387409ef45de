"""Reference commands: the reference state ``x_ref`` at each sample, from the config.

Convention (the paper's and most servo models'): plant state 0 is the position and state 1, where
the plant has it, the velocity; every other entry of ``x_ref`` (further plant states, delayed-input
states of an augmented model) is zero. A step holds the position with zero velocity; a sine carries
its exact derivative as the reference velocity (paper: sin(2 pi t) with 2 pi cos(2 pi t)); a CSV
gives time and position (and optionally velocity; otherwise its central difference) interpolated
linearly at the sample instants and held after its last row.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Protocol

import numpy as np

from dob_hil.config import ReferenceConfig
from dob_hil.errors import ConfigError


class Reference(Protocol):
    def at(self, k: int) -> tuple[float, ...]:
        """The reference state at sample ``k`` (time ``k * period``)."""
        ...


def _state(n_states: int, position: float, velocity: float) -> tuple[float, ...]:
    if n_states == 1:
        return (position,)
    return (position, velocity) + (0.0,) * (n_states - 2)


class StepReference:
    def __init__(self, n_states: int, period_s: float, position: float, start_s: float) -> None:
        self._k_start = math.ceil(start_s / period_s - 1e-9)
        self._before = _state(n_states, 0.0, 0.0)
        self._after = _state(n_states, position, 0.0)

    def at(self, k: int) -> tuple[float, ...]:
        return self._after if k >= self._k_start else self._before


class SineReference:
    def __init__(
        self, n_states: int, period_s: float, amplitude: float, frequency_hz: float, offset: float
    ) -> None:
        self._w = 2.0 * math.pi * frequency_hz
        self._period_s = period_s
        self._amplitude = amplitude
        self._offset = offset
        self._pad = (0.0,) * max(0, n_states - 2)
        self._n = n_states

    def at(self, k: int) -> tuple[float, ...]:
        wt = self._w * (k * self._period_s)
        position = self._offset + self._amplitude * math.sin(wt)
        if self._n == 1:
            return (position,)
        return (position, self._amplitude * self._w * math.cos(wt), *self._pad)


class CsvReference:
    """Columns ``time_s, position[, velocity]`` with a header row; times strictly increasing."""

    def __init__(self, n_states: int, period_s: float, path: Path) -> None:
        times, positions, velocities = read_reference_csv(path)
        self._n = n_states
        self._period_s = period_s
        self._t = np.asarray(times)
        self._p = np.asarray(positions)
        if velocities is None:
            self._v = np.gradient(self._p, self._t) if len(self._t) > 1 else np.zeros(1)
        else:
            self._v = np.asarray(velocities)

    def at(self, k: int) -> tuple[float, ...]:
        t = k * self._period_s
        position = float(np.interp(t, self._t, self._p))
        velocity = float(np.interp(t, self._t, self._v)) if t <= self._t[-1] else 0.0
        return _state(self._n, position, velocity)


MAX_CSV_BYTES = 64 * 1024 * 1024  # 64 MiB: about two million rows
MAX_CSV_VALUE = 1e6  # |position|, |velocity| in output units; times up to this many seconds


def read_reference_csv(path: Path) -> tuple[list[float], list[float], list[float] | None]:
    """Read and check a reference CSV: times, positions and (if the column is there) velocities.

    Errors name the line and the problem, never the file's content (the path may be any file)."""
    name = f"reference.path ({path})"
    try:
        size = path.stat().st_size
        if size > MAX_CSV_BYTES:
            raise ConfigError(name, f"is {size} bytes; at most {MAX_CSV_BYTES} (64 MiB)")
        with path.open(newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except OSError as exc:
        raise ConfigError(name, f"cannot read: {exc.strerror or type(exc).__name__}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(name, f"not UTF-8 text (byte {exc.start} cannot be decoded)") from None
    except csv.Error as exc:
        raise ConfigError(name, f"not a readable CSV file ({str(exc).split(':')[0]})") from None
    if len(rows) < 2:
        raise ConfigError(name, "needs a header row and at least one data row")
    header = [h.strip() for h in rows[0]]
    if (
        header[:2] != ["time_s", "position"]
        or len(header) > 3
        or (len(header) == 3 and header[2] != "velocity")
    ):
        raise ConfigError(name, "line 1: the header must be time_s,position or time_s,position,velocity")
    times: list[float] = []
    positions: list[float] = []
    velocities: list[float] = []
    for line, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise ConfigError(name, f"line {line}: expected {len(header)} columns, got {len(row)}")
        values: list[float] = []
        for column, cell in enumerate(row, start=1):
            try:
                values.append(float(cell))
            except ValueError:
                raise ConfigError(name, f"line {line}, column {column}: not a number") from None
        if not all(math.isfinite(v) for v in values):
            raise ConfigError(name, f"line {line}: non-finite value")
        if any(abs(v) > MAX_CSV_VALUE for v in values):
            raise ConfigError(name, f"line {line}: a value beyond +-{MAX_CSV_VALUE:g}")
        if times and values[0] <= times[-1]:
            raise ConfigError(name, f"line {line}: time {values[0]} does not increase")
        times.append(values[0])
        positions.append(values[1])
        if len(values) == 3:
            velocities.append(values[2])
    if not times:
        raise ConfigError(name, "needs at least one data row")
    return times, positions, velocities if len(header) == 3 else None


def make_reference(config: ReferenceConfig, n_states: int, period_s: float) -> Reference:
    if config.kind == "step":
        return StepReference(n_states, period_s, config.position, config.start_s)
    if config.kind == "sine":
        return SineReference(n_states, period_s, config.amplitude, config.frequency_hz, config.offset)
    if config.csv_path is None:
        raise ConfigError("reference.path", "missing (required for kind = 'csv')")
    return CsvReference(n_states, period_s, config.csv_path)
