"""Reference commands: the reference state ``x_ref`` at each sample, from the config.

Each commanded output follows a position r(t) and its rate r'(t). A step holds the position with
zero rate; a sine carries its exact derivative as the rate (paper: sin(2 pi t) with
2 pi cos(2 pi t)); a CSV gives time and position (and optionally velocity; otherwise its central
difference) interpolated linearly at the sample instants and held after its last row.

``[reference]`` commands output 0 (the other outputs are held at zero); ``[[reference.outputs]]``,
one table per output with the same keys, commands every output.

The reference state is ``x_ref = Nx r + Nv r'`` with the plant's steady-state map
(``state_map = (Nx, Nv)``, n_states x n_outputs each, from
:func:`dob_hil.design.tracking.tracking_map`, Franklin-Powell-Workman), so that every state -- a
two-mass plant's load position, an augmented model's delayed inputs -- gets its steady-state value.
With ``[reference]`` only column 0 of the map is used. Without a map the legacy convention applies:
state 0 is the position, state 1 the velocity, the rest zero; the map of the paper's plant is
exactly that (Nx = [1, 0]', Nv = [0, 1]'). Terms with a zero coefficient are skipped and a unit
coefficient passes the value through, so the paper's x_ref is bit for bit [r, r']; with several
outputs each state is the sum, output by output in order, of its non-zero terms.

:meth:`Reference.block` evaluates n consecutive samples at once, with the same floating-point
operations in the same order as :meth:`Reference.at`: its rows are bit for bit ``at(k)``.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Protocol

import numpy as np
import numpy.typing as npt

from dob_hil.config import ReferenceConfig
from dob_hil.errors import ConfigError

FloatArray = npt.NDArray[np.float64]


class Reference(Protocol):
    def at(self, k: int) -> tuple[float, ...]:
        """The reference state at sample ``k`` (time ``k * period``)."""
        ...

    def block(self, k_start: int, n: int) -> FloatArray:
        """The reference states of samples ``k_start .. k_start + n - 1``, shape (n, n_states):
        row i bit for bit ``at(k_start + i)``."""
        ...


StateMap = tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]


def _sample_times(k_start: int, n: int, period_s: float) -> FloatArray:
    """``k * period_s`` for each k, as ``at`` computes it (an int times a float: k converted exactly)."""
    ks = np.arange(k_start, k_start + n, dtype=np.int64).astype(np.float64)
    return np.asarray(ks * period_s, dtype=np.float64)


# ---------------------------------------------------------------------------------------------
# One output's command: (position, rate) at a sample, and for a block of samples.
# ---------------------------------------------------------------------------------------------
class _Signal(Protocol):
    def pr(self, k: int) -> tuple[float, float]: ...

    def pr_block(self, k_start: int, n: int) -> tuple[FloatArray, FloatArray]: ...


class _StepSignal:
    def __init__(self, period_s: float, position: float, start_s: float) -> None:
        self.k_start = math.ceil(start_s / period_s - 1e-9)
        self.position = position

    def pr(self, k: int) -> tuple[float, float]:
        return (self.position, 0.0) if k >= self.k_start else (0.0, 0.0)

    def pr_block(self, k_start: int, n: int) -> tuple[FloatArray, FloatArray]:
        ks = np.arange(k_start, k_start + n, dtype=np.int64)
        return np.where(ks >= self.k_start, self.position, 0.0), np.zeros(n)


class _SineSignal:
    def __init__(self, period_s: float, amplitude: float, frequency_hz: float, offset: float) -> None:
        self._w = 2.0 * math.pi * frequency_hz
        self._period_s = period_s
        self._amplitude = amplitude
        self._offset = offset

    def pr(self, k: int) -> tuple[float, float]:
        wt = self._w * (k * self._period_s)
        return self._offset + self._amplitude * math.sin(wt), self._amplitude * self._w * math.cos(wt)

    def pr_block(self, k_start: int, n: int) -> tuple[FloatArray, FloatArray]:
        wt = self._w * _sample_times(k_start, n, self._period_s)
        angles = wt.tolist()
        # math.sin/cos, not np.sin/cos: numpy's (SIMD) kernels may differ from libm in the last bit
        sin = np.fromiter(map(math.sin, angles), dtype=np.float64, count=n)
        cos = np.fromiter(map(math.cos, angles), dtype=np.float64, count=n)
        position = self._offset + self._amplitude * sin
        return np.asarray(position), np.asarray(self._amplitude * self._w * cos)


class _CsvSignal:
    """Columns ``time_s, position[, velocity]`` with a header row; times strictly increasing."""

    def __init__(self, period_s: float, path: Path) -> None:
        times, positions, velocities = read_reference_csv(path)
        self._period_s = period_s
        self._t = np.asarray(times)
        self._p = np.asarray(positions)
        if velocities is None:
            self._v = _derived_velocity(times, positions)
        else:
            self._v = np.asarray(velocities)

    def pr(self, k: int) -> tuple[float, float]:
        t = k * self._period_s
        position = float(np.interp(t, self._t, self._p))
        velocity = float(np.interp(t, self._t, self._v)) if t <= self._t[-1] else 0.0
        return position, velocity

    def pr_block(self, k_start: int, n: int) -> tuple[FloatArray, FloatArray]:
        t = _sample_times(k_start, n, self._period_s)
        position = np.interp(t, self._t, self._p)
        velocity = np.where(t <= self._t[-1], np.interp(t, self._t, self._v), 0.0)
        return np.asarray(position, dtype=np.float64), np.asarray(velocity, dtype=np.float64)


def _signal(config: ReferenceConfig, period_s: float, name: str = "reference") -> _Signal:
    if config.kind == "step":
        return _StepSignal(period_s, config.position, config.start_s)
    if config.kind == "sine":
        return _SineSignal(period_s, config.amplitude, config.frequency_hz, config.offset)
    if config.csv_path is None:
        raise ConfigError(f"{name}.path", "missing (required for kind = 'csv')")
    return _CsvSignal(period_s, config.csv_path)


# ---------------------------------------------------------------------------------------------
# From (position, rate) per output to the reference state.
# ---------------------------------------------------------------------------------------------
def _term(a: float, b: float, position: float, rate: float) -> float:
    """a * position + b * rate with zero terms skipped and unit coefficients exact."""
    if b == 0.0:
        return 0.0 if a == 0.0 else position if a == 1.0 else a * position
    if a == 0.0:
        return rate if b == 1.0 else b * rate
    return a * position + b * rate


def _term_block(a: float, b: float, position: FloatArray, rate: FloatArray) -> FloatArray:
    """:func:`_term` element by element (the same operations)."""
    if b == 0.0:
        return np.zeros_like(position) if a == 0.0 else position.copy() if a == 1.0 else a * position
    if a == 0.0:
        return rate.copy() if b == 1.0 else b * rate
    return np.asarray(a * position + b * rate)


class StateOf:
    """x_ref from one output's (position, rate): per state a * position + b * rate, with column
    ``output`` of the map (zero and unit terms exact)."""

    def __init__(self, n_states: int, state_map: StateMap | None, output: int = 0) -> None:
        if state_map is None:
            a = [1.0] + [0.0] * (n_states - 1)
            b = ([0.0, 1.0] + [0.0] * (n_states - 2)) if n_states > 1 else [0.0]
        else:
            Nx, Nv = _checked_map(n_states, state_map, output + 1)
            a = [float(v) for v in Nx[:, output]]
            b = [float(v) for v in Nv[:, output]]
        self._terms = tuple(zip(a, b, strict=True))

    def __call__(self, position: float, rate: float) -> tuple[float, ...]:
        return tuple(_term(a, b, position, rate) for a, b in self._terms)

    def block(self, position: FloatArray, rate: FloatArray) -> FloatArray:
        out = np.empty((len(position), len(self._terms)), dtype=np.float64)
        for s, (a, b) in enumerate(self._terms):
            out[:, s] = _term_block(a, b, position, rate)
        return out


def _checked_map(n_states: int, state_map: StateMap, n_outputs: int) -> StateMap:
    Nx, Nv = state_map
    if Nx.shape[0] != n_states or Nv.shape[0] != n_states:
        raise ConfigError("reference", f"state map has {Nx.shape[0]} rows, the model {n_states} states")
    if Nx.ndim != 2 or Nx.shape[1] < n_outputs or Nv.shape != Nx.shape:
        raise ConfigError(
            "reference.outputs",
            f"{n_outputs} outputs commanded, the state map has {Nx.shape[1] if Nx.ndim == 2 else 0} columns",
        )
    return Nx, Nv


# ---------------------------------------------------------------------------------------------
# References
# ---------------------------------------------------------------------------------------------
class _SingleOutput:
    """Output 0 commanded by one signal (``[reference]``), the others held at zero."""

    def __init__(self, signal: _Signal, n_states: int, state_map: StateMap | None) -> None:
        self._signal = signal
        self._state = StateOf(n_states, state_map)

    def at(self, k: int) -> tuple[float, ...]:
        return self._state(*self._signal.pr(k))

    def block(self, k_start: int, n: int) -> FloatArray:
        return self._state.block(*self._signal.pr_block(k_start, n))


class StepReference(_SingleOutput):
    def __init__(
        self,
        n_states: int,
        period_s: float,
        position: float,
        start_s: float,
        state_map: StateMap | None = None,
    ) -> None:
        signal = _StepSignal(period_s, position, start_s)
        super().__init__(signal, n_states, state_map)
        self._k_start = signal.k_start
        self._before = self._state(0.0, 0.0)
        self._after = self._state(position, 0.0)

    def at(self, k: int) -> tuple[float, ...]:
        return self._after if k >= self._k_start else self._before


class SineReference(_SingleOutput):
    def __init__(
        self,
        n_states: int,
        period_s: float,
        amplitude: float,
        frequency_hz: float,
        offset: float,
        state_map: StateMap | None = None,
    ) -> None:
        super().__init__(_SineSignal(period_s, amplitude, frequency_hz, offset), n_states, state_map)


class CsvReference(_SingleOutput):
    """Columns ``time_s, position[, velocity]`` with a header row; times strictly increasing."""

    def __init__(self, n_states: int, period_s: float, path: Path, state_map: StateMap | None = None) -> None:
        super().__init__(_CsvSignal(period_s, path), n_states, state_map)


class MultiOutputReference:
    """Every output commanded by its own signal (``[[reference.outputs]]``): state s of x_ref is the
    sum, output by output, of ``Nx[s, j] r_j + Nv[s, j] r_j'`` over the outputs j whose
    coefficients are not both zero (0.0 where none is)."""

    def __init__(self, signals: Sequence[_Signal], n_states: int, state_map: StateMap) -> None:
        Nx, Nv = _checked_map(n_states, state_map, len(signals))
        self._signals = tuple(signals)
        self._n_states = n_states
        self._terms = tuple(
            tuple(
                (j, float(Nx[s, j]), float(Nv[s, j]))
                for j in range(len(signals))
                if not (Nx[s, j] == 0.0 and Nv[s, j] == 0.0)
            )
            for s in range(n_states)
        )

    def at(self, k: int) -> tuple[float, ...]:
        prs = [signal.pr(k) for signal in self._signals]
        out = []
        for terms in self._terms:
            acc = 0.0
            for i, (j, a, b) in enumerate(terms):
                value = _term(a, b, *prs[j])
                acc = value if i == 0 else acc + value
            out.append(acc)
        return tuple(out)

    def block(self, k_start: int, n: int) -> FloatArray:
        prs = [signal.pr_block(k_start, n) for signal in self._signals]
        out = np.zeros((n, self._n_states), dtype=np.float64)
        for s, terms in enumerate(self._terms):
            for i, (j, a, b) in enumerate(terms):
                value = _term_block(a, b, *prs[j])
                out[:, s] = value if i == 0 else out[:, s] + value
        return out


MAX_CSV_BYTES = 64 * 1024 * 1024  # 64 MiB: about two million rows
MAX_CSV_VALUE = 1e6  # |position|, |velocity| in output units; times up to this many seconds
# |velocity| derived from positions alone: above any rate a configured sine reaches (1e6 at Nyquist
# of a 1 us period is about 3e12); beyond it the rows are simply too close in time
MAX_DERIVED_VELOCITY = 1e13


def read_reference_csv(
    path: Path, field: str = "reference.path"
) -> tuple[list[float], list[float], list[float] | None]:
    """Read and check a reference CSV: times, positions and (if the column is there) velocities;
    without a velocity column the central difference the run will command is checked too.

    Errors name ``field`` (the config key that points at the file), the line and the problem, never
    the file's content (the path may be any file)."""
    name = f"{field} ({path})"
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
    if len(header) == 2:
        _check_derived_velocity(name, times, positions)
    return times, positions, velocities if len(header) == 3 else None


def _derived_velocity(times: Sequence[float], positions: Sequence[float]) -> FloatArray:
    """The velocity column's stand-in: the central difference of the positions over the times."""
    if len(times) < 2:
        return np.zeros(1)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        return np.asarray(np.gradient(np.asarray(positions), np.asarray(times)), dtype=np.float64)


def _check_derived_velocity(name: str, times: Sequence[float], positions: Sequence[float]) -> None:
    """Rows too close in time make the central difference huge or infinite: refused here, with the
    line, instead of commanding it mid-run."""
    velocity = _derived_velocity(times, positions)
    bad = np.flatnonzero(~(np.abs(velocity) <= MAX_DERIVED_VELOCITY))
    if bad.size:
        raise ConfigError(
            name,
            f"data row {int(bad[0]) + 1}: the velocity derived from the positions (central difference) is "
            f"beyond +-{MAX_DERIVED_VELOCITY:g} (rows too close in time?); give a velocity column "
            "or space the rows",
        )


def make_reference(
    config: ReferenceConfig, n_states: int, period_s: float, *, state_map: StateMap | None = None
) -> Reference:
    """The configured reference; ``state_map = (Nx, Nv)`` (module docstring), None: the legacy map
    (one commanded output only: several need the plant's map). One ``[[reference.outputs]]``
    table is the same reference as ``[reference]`` with its keys, bit for bit."""
    if len(config.outputs) == 1:
        config = config.outputs[0]
    if config.outputs:
        if state_map is None:
            raise ConfigError("reference.outputs", "several commanded outputs need the plant's state map")
        signals = [_signal(c, period_s, f"reference.outputs[{i}]") for i, c in enumerate(config.outputs)]
        return MultiOutputReference(signals, n_states, state_map)
    if config.kind == "step":
        return StepReference(n_states, period_s, config.position, config.start_s, state_map)
    if config.kind == "sine":
        c = config
        return SineReference(n_states, period_s, c.amplitude, c.frequency_hz, c.offset, state_map)
    if config.csv_path is None:
        raise ConfigError("reference.path", "missing (required for kind = 'csv')")
    return CsvReference(n_states, period_s, config.csv_path, state_map)
