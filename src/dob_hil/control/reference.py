"""Reference commands: the reference state ``x_ref`` at each sample, from the config.

The config commands output 0 with a position r(t) and its rate r'(t) (the other outputs are held at
zero). A step holds the position with zero rate; a sine carries its exact derivative as the rate
(paper: sin(2 pi t) with 2 pi cos(2 pi t)); a CSV gives time and position (and optionally velocity;
otherwise its central difference) interpolated linearly at the sample instants and held after its
last row.

The reference state is ``x_ref = Nx[:, 0] r + Nv[:, 0] r'`` with the plant's steady-state map
(``state_map = (Nx, Nv)`` from :func:`dob_hil.design.tracking.tracking_map`, Franklin-Powell-Workman),
so that every state -- a two-mass plant's load position, an augmented model's delayed inputs --
gets its steady-state value. Without a map the legacy convention applies: state 0 is the position,
state 1 the velocity, the rest zero; the map of the paper's plant is exactly that (Nx = [1, 0]',
Nv = [0, 1]'), and terms with a zero coefficient are skipped and a unit coefficient passes the value
through, so its x_ref is bit for bit the paper's [r, r'].
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Protocol

import numpy as np
import numpy.typing as npt

from dob_hil.config import ReferenceConfig
from dob_hil.errors import ConfigError


class Reference(Protocol):
    def at(self, k: int) -> tuple[float, ...]:
        """The reference state at sample ``k`` (time ``k * period``)."""
        ...


StateMap = tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]


class StateOf:
    """x_ref from (position, rate): per state a * position + b * rate, zero and unit terms exact."""

    def __init__(self, n_states: int, state_map: StateMap | None) -> None:
        if state_map is None:
            a = [1.0] + [0.0] * (n_states - 1)
            b = ([0.0, 1.0] + [0.0] * (n_states - 2)) if n_states > 1 else [0.0]
        else:
            Nx, Nv = state_map
            if Nx.shape[0] != n_states or Nv.shape[0] != n_states:
                raise ConfigError(
                    "reference", f"state map has {Nx.shape[0]} rows, the model {n_states} states"
                )
            a = [float(v) for v in Nx[:, 0]]
            b = [float(v) for v in Nv[:, 0]]
        self._terms = tuple(zip(a, b, strict=True))

    def __call__(self, position: float, rate: float) -> tuple[float, ...]:
        out = []
        for a, b in self._terms:
            if b == 0.0:
                out.append(0.0 if a == 0.0 else position if a == 1.0 else a * position)
            elif a == 0.0:
                out.append(rate if b == 1.0 else b * rate)
            else:
                out.append(a * position + b * rate)
        return tuple(out)


class StepReference:
    def __init__(
        self,
        n_states: int,
        period_s: float,
        position: float,
        start_s: float,
        state_map: StateMap | None = None,
    ) -> None:
        state = StateOf(n_states, state_map)
        self._k_start = math.ceil(start_s / period_s - 1e-9)
        self._before = state(0.0, 0.0)
        self._after = state(position, 0.0)

    def at(self, k: int) -> tuple[float, ...]:
        return self._after if k >= self._k_start else self._before


class SineReference:
    def __init__(
        self,
        n_states: int,
        period_s: float,
        amplitude: float,
        frequency_hz: float,
        offset: float,
        state_map: StateMap | None = None,
    ) -> None:
        self._w = 2.0 * math.pi * frequency_hz
        self._period_s = period_s
        self._amplitude = amplitude
        self._offset = offset
        self._state = StateOf(n_states, state_map)

    def at(self, k: int) -> tuple[float, ...]:
        wt = self._w * (k * self._period_s)
        position = self._offset + self._amplitude * math.sin(wt)
        return self._state(position, self._amplitude * self._w * math.cos(wt))


class CsvReference:
    """Columns ``time_s, position[, velocity]`` with a header row; times strictly increasing."""

    def __init__(self, n_states: int, period_s: float, path: Path, state_map: StateMap | None = None) -> None:
        times, positions, velocities = read_reference_csv(path)
        self._state = StateOf(n_states, state_map)
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
        return self._state(position, velocity)


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


def make_reference(
    config: ReferenceConfig, n_states: int, period_s: float, *, state_map: StateMap | None = None
) -> Reference:
    """The configured reference; ``state_map = (Nx, Nv)`` (module docstring), None: the legacy map."""
    if config.kind == "step":
        return StepReference(n_states, period_s, config.position, config.start_s, state_map)
    if config.kind == "sine":
        c = config
        return SineReference(n_states, period_s, c.amplitude, c.frequency_hz, c.offset, state_map)
    if config.csv_path is None:
        raise ConfigError("reference.path", "missing (required for kind = 'csv')")
    return CsvReference(n_states, period_s, config.csv_path, state_map)
