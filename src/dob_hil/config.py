"""The TOML configuration: plant, design, drive, simulated drive, reference and run settings.

Parsed as data only (``tomllib``), validated field by field; every problem raises
:class:`~dob_hil.errors.ConfigError` naming the dotted field and what is wrong with it.
Unknown keys are errors too, so a typo never silently falls back to a default.
"""

from __future__ import annotations

import difflib
import math
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from dob_hil.errors import ConfigError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

Matrix = npt.NDArray[np.float64]

MISSING_FEEDBACK_POLICIES = ("hold", "extrapolate", "zero")
REFERENCE_KINDS = ("step", "sine", "csv")
DISTURBANCE_KINDS = ("sine", "step", "noise")
DRIVE_PROFILES = ("native",)


# ---------------------------------------------------------------------------------------------
# Section reader: typed getters that name the field on every error and reject unknown keys.
# ---------------------------------------------------------------------------------------------
class _Section:
    def __init__(self, data: object, path: str) -> None:
        if not isinstance(data, Mapping):
            raise ConfigError(path or "<root>", f"expected a table, got {_kind(data)}")
        self.data: Mapping[str, Any] = data
        self.path = path
        self.used: set[str] = set()

    def name(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def has(self, key: str) -> bool:
        return key in self.data

    def raw(self, key: str) -> object:
        self.used.add(key)
        return self.data[key]

    def sub(self, key: str, required: bool = False) -> _Section:
        if key not in self.data:
            if required:
                raise ConfigError(self.name(key), "missing (a required table)")
            return _Section({}, self.name(key))
        return _Section(self.raw(key), self.name(key))

    def number(
        self,
        key: str,
        default: float | None = None,
        *,
        positive: bool = False,
        nonnegative: bool = False,
        below: float | None = None,
    ) -> float:
        if key not in self.data:
            if default is None:
                raise ConfigError(self.name(key), "missing (a required number)")
            return default
        value = self.raw(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(self.name(key), f"expected a number, got {_kind(value)}")
        x = float(value)
        if not math.isfinite(x):
            raise ConfigError(self.name(key), f"must be finite, got {x}")
        if positive and x <= 0:
            raise ConfigError(self.name(key), f"must be > 0, got {x:g}")
        if nonnegative and x < 0:
            raise ConfigError(self.name(key), f"must be >= 0, got {x:g}")
        if below is not None and x >= below:
            raise ConfigError(self.name(key), f"must be < {below:g}, got {x:g}")
        return x

    def optional_number(self, key: str, *, positive: bool = False) -> float | None:
        if key not in self.data:
            return None
        return self.number(key, positive=positive)

    def integer(
        self, key: str, default: int | None = None, *, low: int | None = None, high: int | None = None
    ) -> int:
        if key not in self.data:
            if default is None:
                raise ConfigError(self.name(key), "missing (a required integer)")
            return default
        value = self.raw(key)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(self.name(key), f"expected an integer, got {_kind(value)}")
        if low is not None and value < low:
            raise ConfigError(self.name(key), f"must be >= {low}, got {value}")
        if high is not None and value > high:
            raise ConfigError(self.name(key), f"must be <= {high}, got {value}")
        return value

    def boolean(self, key: str, default: bool) -> bool:
        if key not in self.data:
            return default
        value = self.raw(key)
        if not isinstance(value, bool):
            raise ConfigError(self.name(key), f"expected true or false, got {_kind(value)}")
        return value

    def string(self, key: str, default: str | None = None, choices: tuple[str, ...] = ()) -> str:
        if key not in self.data:
            if default is None:
                raise ConfigError(self.name(key), "missing (a required string)")
            return default
        value = self.raw(key)
        if not isinstance(value, str):
            raise ConfigError(self.name(key), f"expected a string, got {_kind(value)}")
        if choices and value not in choices:
            raise ConfigError(self.name(key), f"must be one of {', '.join(choices)}; got {value!r}")
        return value

    def strings(self, key: str) -> tuple[str, ...] | None:
        if key not in self.data:
            return None
        value = self.raw(key)
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise ConfigError(self.name(key), f"expected a list of strings, got {_kind(value)}")
        return tuple(value)

    def integers(self, key: str) -> tuple[int, ...] | None:
        if key not in self.data:
            return None
        value = self.raw(key)
        if not isinstance(value, list) or not all(
            isinstance(v, int) and not isinstance(v, bool) for v in value
        ):
            raise ConfigError(self.name(key), f"expected a list of integers, got {_kind(value)}")
        return tuple(value)

    def numbers(self, key: str, *, positive: bool = False) -> tuple[float, ...] | None:
        if key not in self.data:
            return None
        arr = self.matrix(key)
        if arr is None or (arr.shape[0] != 1 and arr.shape[1] != 1):
            raise ConfigError(self.name(key), "expected a list of numbers")
        flat = tuple(float(v) for v in arr.ravel())
        if positive and any(v <= 0 for v in flat):
            raise ConfigError(self.name(key), "every value must be > 0")
        return flat

    def matrix(self, key: str, shape: tuple[int | None, int | None] | None = None) -> Matrix | None:
        """A 2-D float matrix. A flat list is a row vector; ``shape`` entries of None are free."""
        if key not in self.data:
            return None
        return parse_matrix(self.raw(key), self.name(key), shape)

    def finish(self) -> None:
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            key = unknown[0]
            close = difflib.get_close_matches(key, [str(k) for k in self.data if k in self.used])
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ConfigError(self.name(key), f"unknown key{hint}")


def _kind(value: object) -> str:
    if isinstance(value, bool):
        return f"boolean {value}"
    if isinstance(value, (int, float)):
        return f"number {value}"
    if isinstance(value, str):
        return f"string {value!r}"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, Mapping):
        return "a table"
    return type(value).__name__


def parse_matrix(value: object, name: str, shape: tuple[int | None, int | None] | None = None) -> Matrix:
    """Parse a TOML number, list or list of lists into a finite 2-D float64 array."""
    if isinstance(value, bool):
        raise ConfigError(name, f"expected a matrix of numbers, got {_kind(value)}")
    if isinstance(value, (int, float)):
        rows: list[list[object]] = [[value]]
    elif isinstance(value, list):
        if not value:
            raise ConfigError(name, "expected a matrix of numbers, got an empty list")
        if all(isinstance(r, list) for r in value):
            rows = [list(r) for r in value]
        elif any(isinstance(r, list) for r in value):
            raise ConfigError(name, "mixes numbers and rows; write a list of rows")
        else:
            rows = [list(value)]
    else:
        raise ConfigError(name, f"expected a matrix of numbers, got {_kind(value)}")
    width = len(rows[0])
    if width == 0:
        raise ConfigError(name, "has an empty row")
    for i, row in enumerate(rows):
        if len(row) != width:
            raise ConfigError(name, f"row {i} has {len(row)} entries, row 0 has {width}")
        for j, v in enumerate(row):
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ConfigError(name, f"entry [{i}][{j}] is {_kind(v)}, expected a number")
            if not math.isfinite(float(v)):
                raise ConfigError(name, f"entry [{i}][{j}] must be finite, got {v}")
    arr = np.array(rows, dtype=np.float64)
    if shape is not None and arr.shape[0] == 1 and shape[1] == 1 and shape[0] != 1:
        arr = arr.T  # a flat list where a column is expected: ``Lc = [0.75, 0.5]``
    if shape is not None:
        want_r, want_c = shape
        if (want_r is not None and arr.shape[0] != want_r) or (want_c is not None and arr.shape[1] != want_c):
            want = f"{'n' if want_r is None else want_r}x{'n' if want_c is None else want_c}"
            raise ConfigError(name, f"expected shape {want}, got {arr.shape[0]}x{arr.shape[1]}")
    return arr


# ---------------------------------------------------------------------------------------------
# The configuration dataclasses
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PlantConfig:
    A: Matrix
    B: Matrix
    C: Matrix
    period_ns: int
    input_delay_samples: int = 0
    state_names: tuple[str, ...] = ()
    input_names: tuple[str, ...] = ()
    output_names: tuple[str, ...] = ()
    input_unit: str = "A"
    output_unit: str = "unit"

    @property
    def n_states(self) -> int:
        return int(self.A.shape[0])

    @property
    def n_inputs(self) -> int:
        return int(self.B.shape[1])

    @property
    def n_outputs(self) -> int:
        return int(self.C.shape[0])

    @property
    def period_s(self) -> float:
        return self.period_ns * 1e-9


@dataclass(frozen=True)
class EstimatorConfig:
    """Either an explicit ``Lc`` or the DARE weights ``Gam1`` (process) and ``D1`` (sensor)."""

    Lc: Matrix | None = None
    Gam1: Matrix | None = None
    D1: Matrix | None = None


@dataclass(frozen=True)
class FeedbackConfig:
    """Either an explicit ``Kc`` or the LTR DARE with ``R1 = q C'C`` and ``R2``."""

    Kc: Matrix | None = None
    q: float | None = None
    R2: Matrix | None = None
    ltr_q_values: tuple[float, ...] | None = None


@dataclass(frozen=True)
class DobConfig:
    """Either an explicit ``Kdist`` or a design method with its parameter."""

    Kdist: Matrix | None = None
    method: str | None = None
    gain: float | None = None


@dataclass(frozen=True)
class DesignConfig:
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    feedback: FeedbackConfig = field(default_factory=FeedbackConfig)
    dob: DobConfig = field(default_factory=DobConfig)


@dataclass(frozen=True)
class DriveConfig:
    profile: str = "native"
    node_id: int = 1
    bitrate_bps: int = 1_000_000
    current_limit_A: float = 0.7
    dac_lsb_A: float = 1.0 / 2048.0
    encoder_counts_per_unit: float = 10000.0
    encoder_bits: int = 32
    watchdog_periods: int = 10
    feedback_timeout_periods: int = 10
    clear_fault: bool = False  # send ClearFault before enabling (recover a drive left in FAULT)


@dataclass(frozen=True)
class DisturbanceConfig:
    kind: str
    amplitude_A: float = 0.0
    frequency_hz: float = 0.0
    phase_rad: float = 0.0
    start_s: float = 0.0
    std_A: float = 0.0
    seed: int = 0
    input_index: int = 0


@dataclass(frozen=True)
class FaultsConfig:
    """``[sim.faults]``: faults the simulated drive injects on its own, at a simulated time.

    Each ``*_at_s`` is a time after the drive's first enable, turned into a number of periods
    ``round(t / Ts)`` (at least 1); None: never.
    ``fault_at_s``: the drive enters FAULT (code OVERCURRENT). ``silent_at_s``: the drive stops
    sending any frame (it still acts on what it receives). ``encoder_jump_at_s``: the encoder
    counter steps by ``encoder_jump_counts`` and keeps the offset.
    """

    fault_at_s: float | None = None
    silent_at_s: float | None = None
    encoder_jump_at_s: float | None = None
    encoder_jump_counts: int = 0

    @property
    def active(self) -> bool:
        return (
            self.fault_at_s is not None
            or self.silent_at_s is not None
            or (self.encoder_jump_at_s is not None and self.encoder_jump_counts != 0)
        )


@dataclass(frozen=True)
class SimConfig:
    substeps: int = 10
    noise_counts_std: float = 0.0
    seed: int = 0
    latency_us: float = 0.0
    jitter_us: float = 0.0
    loss_probability: float = 0.0
    initial_state: tuple[float, ...] | None = None
    disturbances: tuple[DisturbanceConfig, ...] = ()
    faults: FaultsConfig = field(default_factory=FaultsConfig)


@dataclass(frozen=True)
class ReferenceConfig:
    kind: str = "step"
    position: float = 1.0
    start_s: float = 0.0
    amplitude: float = 1.0
    frequency_hz: float = 1.0
    offset: float = 0.0
    csv_path: Path | None = None


@dataclass(frozen=True)
class RunConfig:
    duration_s: float = 1.0
    dob_enabled: bool = True
    log_dir: Path = Path("logs")
    missing_feedback_policy: str = "hold"
    max_missing_periods: int = 3
    sched_fifo: bool = False
    cpu_affinity: tuple[int, ...] | None = None
    freeze_gc: bool = False


@dataclass(frozen=True)
class Config:
    name: str
    plant: PlantConfig
    design: DesignConfig
    drive: DriveConfig
    sim: SimConfig
    reference: ReferenceConfig
    run: RunConfig
    source: Path | None = None
    text: str = ""


# ---------------------------------------------------------------------------------------------
# Parsing
# ---------------------------------------------------------------------------------------------
def load_config(path: str | Path) -> Config:
    """Read and validate a TOML config file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(str(p), "no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(str(p), f"cannot read: {exc}") from None
    return parse_config_text(text, source=p)


def parse_config_text(text: str, source: Path | None = None) -> Config:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(str(source) if source else "<config>", f"not valid TOML: {exc}") from None
    return parse_config(data, source=source, text=text)


def parse_config(data: Mapping[str, Any], source: Path | None = None, text: str = "") -> Config:
    root = _Section(data, "")
    base_dir = source.parent if source is not None else Path.cwd()
    meta = root.sub("meta")
    name = meta.string("name", source.stem if source else "config")
    meta.string("description", "")
    meta.finish()
    plant = _parse_plant(root.sub("plant", required=True))
    design = _parse_design(root.sub("design"), plant)
    drive = _parse_drive(root.sub("drive"))
    sim = _parse_sim(root.sub("sim"), plant)
    reference = _parse_reference(root.sub("reference"), base_dir)
    run = _parse_run(root.sub("run"))
    root.finish()
    return Config(name, plant, design, drive, sim, reference, run, source, text)


def _parse_plant(s: _Section) -> PlantConfig:
    A = s.matrix("A")
    if A is None:
        raise ConfigError(s.name("A"), "missing (the continuous state matrix)")
    if A.shape[0] != A.shape[1]:
        raise ConfigError(s.name("A"), f"must be square, got {A.shape[0]}x{A.shape[1]}")
    n = A.shape[0]
    B = s.matrix("B", (n, None) if n == 1 else None)
    if B is None:
        raise ConfigError(s.name("B"), "missing (the continuous input matrix)")
    if B.shape[0] == 1 and B.shape[1] == n and n != 1:
        B = B.T  # a flat list where a column is meant: ``B = [0.0, 2.1484e4]``
    if B.shape[0] != n:
        raise ConfigError(s.name("B"), f"must have {n} rows (A is {n}x{n}), got {B.shape[0]}")
    C = s.matrix("C", (None, n))
    if C is None:
        raise ConfigError(s.name("C"), "missing (the output matrix)")
    period_us = s.number("period_us", positive=True)
    if period_us > 1e6:
        raise ConfigError(s.name("period_us"), f"must be <= 1e6 us (1 s) for a servo loop, got {period_us:g}")
    period_ns = round(period_us * 1000.0)
    if period_ns <= 0 or abs(period_ns - period_us * 1000.0) > 1e-6 * max(1.0, period_us):
        raise ConfigError(s.name("period_us"), f"must be a whole number of ns, got {period_us} us")
    delay = s.integer("input_delay_samples", 0, low=0, high=100)
    state_names = s.strings("state_names") or tuple(f"x{i + 1}" for i in range(n))
    input_names = s.strings("input_names") or tuple(f"u{i + 1}" for i in range(B.shape[1]))
    output_names = s.strings("output_names") or tuple(f"y{i + 1}" for i in range(C.shape[0]))
    for key, names, count in (
        ("state_names", state_names, n),
        ("input_names", input_names, B.shape[1]),
        ("output_names", output_names, C.shape[0]),
    ):
        if len(names) != count:
            raise ConfigError(s.name(key), f"expected {count} names, got {len(names)}")
    input_unit = s.string("input_unit", "A")
    output_unit = s.string("output_unit", "unit")
    s.finish()
    return PlantConfig(
        A, B, C, period_ns, delay, state_names, input_names, output_names, input_unit, output_unit
    )


def _parse_design(s: _Section, plant: PlantConfig) -> DesignConfig:
    n_aug = plant.n_states + plant.input_delay_samples * plant.n_inputs
    p, m = plant.n_outputs, plant.n_inputs
    e = s.sub("estimator")
    est = EstimatorConfig(
        Lc=e.matrix("Lc", (n_aug, p)),
        Gam1=e.matrix("Gam1", (n_aug, None)),
        D1=e.matrix("D1", (p, None)),
    )
    if est.Lc is not None and (est.Gam1 is not None or est.D1 is not None):
        raise ConfigError(e.name("Lc"), "give either Lc or the DARE weights Gam1/D1, not both")
    e.finish()
    f = s.sub("feedback")
    fb = FeedbackConfig(
        Kc=f.matrix("Kc", (m, n_aug)),
        q=f.optional_number("q", positive=True),
        R2=f.matrix("R2", (m, m)),
        ltr_q_values=f.numbers("ltr_q_values", positive=True),
    )
    if fb.Kc is not None and (fb.q is not None or fb.R2 is not None):
        raise ConfigError(f.name("Kc"), "give either Kc or the LTR weights q/R2, not both")
    f.finish()
    d = s.sub("dob")
    dob = DobConfig(
        Kdist=d.matrix("Kdist", (m, n_aug)),
        method=d.string("method", "") or None,
        gain=d.optional_number("gain", positive=True),
    )
    if dob.Kdist is not None and dob.method is not None:
        raise ConfigError(d.name("Kdist"), "give either Kdist or a design method, not both")
    d.finish()
    s.finish()
    return DesignConfig(est, fb, dob)


def _parse_drive(s: _Section) -> DriveConfig:
    d = DriveConfig(
        profile=s.string("profile", "native", DRIVE_PROFILES),
        node_id=s.integer("node_id", 1, low=0, high=127),
        bitrate_bps=s.integer("bitrate_bps", 1_000_000, low=10_000, high=8_000_000),
        current_limit_A=s.number("current_limit_A", 0.7, positive=True),
        dac_lsb_A=s.number("dac_lsb_A", 1.0 / 2048.0, positive=True),
        encoder_counts_per_unit=s.number("encoder_counts_per_unit", 10000.0, positive=True),
        encoder_bits=s.integer("encoder_bits", 32, low=8, high=32),
        watchdog_periods=s.integer("watchdog_periods", 10, low=1, high=100_000),
        feedback_timeout_periods=s.integer("feedback_timeout_periods", 10, low=1, high=100_000),
        clear_fault=s.boolean("clear_fault", False),
    )
    if d.current_limit_A / d.dac_lsb_A > 32767:
        raise ConfigError(
            s.name("current_limit_A"),
            f"{d.current_limit_A} A is {d.current_limit_A / d.dac_lsb_A:.0f} DAC LSBs; "
            "the int16 current command holds at most 32767",
        )
    if d.current_limit_A < d.dac_lsb_A:
        raise ConfigError(s.name("current_limit_A"), "is smaller than one DAC LSB")
    s.finish()
    return d


def _parse_sim(s: _Section, plant: PlantConfig) -> SimConfig:
    dists: list[DisturbanceConfig] = []
    if s.has("disturbance"):
        raw = s.raw("disturbance")
        if not isinstance(raw, list):
            raise ConfigError(s.name("disturbance"), "expected an array of tables [[sim.disturbance]]")
        for i, item in enumerate(raw):
            ds = _Section(item, f"{s.name('disturbance')}[{i}]")
            kind = ds.string("kind", choices=DISTURBANCE_KINDS)
            dists.append(
                DisturbanceConfig(
                    kind=kind,
                    amplitude_A=ds.number("amplitude_A", 0.0),
                    frequency_hz=ds.number("frequency_hz", 0.0, nonnegative=True),
                    phase_rad=ds.number("phase_rad", 0.0),
                    start_s=ds.number("start_s", 0.0, nonnegative=True),
                    std_A=ds.number("std_A", 0.0, nonnegative=True),
                    seed=ds.integer("seed", 0, low=0),
                    input_index=ds.integer("input_index", 0, low=0, high=plant.n_inputs - 1),
                )
            )
            ds.finish()
    init = s.numbers("initial_state")
    if init is not None and len(init) != plant.n_states:
        raise ConfigError(s.name("initial_state"), f"expected {plant.n_states} values, got {len(init)}")
    sim = SimConfig(
        substeps=s.integer("substeps", 10, low=1, high=10_000),
        noise_counts_std=s.number("noise_counts_std", 0.0, nonnegative=True),
        seed=s.integer("seed", 0, low=0),
        latency_us=s.number("latency_us", 0.0, nonnegative=True),
        jitter_us=s.number("jitter_us", 0.0, nonnegative=True),
        loss_probability=s.number("loss_probability", 0.0, nonnegative=True, below=1.0),
        initial_state=init,
        disturbances=tuple(dists),
        faults=_parse_faults(s.sub("faults")),
    )
    s.finish()
    return sim


def _parse_faults(s: _Section) -> FaultsConfig:
    faults = FaultsConfig(
        fault_at_s=s.optional_number("fault_at_s", positive=True),
        silent_at_s=s.optional_number("silent_at_s", positive=True),
        encoder_jump_at_s=s.optional_number("encoder_jump_at_s", positive=True),
        encoder_jump_counts=s.integer("encoder_jump_counts", 0, low=-(2**31), high=2**31 - 1),
    )
    if faults.encoder_jump_at_s is not None and faults.encoder_jump_counts == 0:
        raise ConfigError(s.name("encoder_jump_counts"), "missing or 0: give the jump's size in counts")
    s.finish()
    return faults


def _parse_reference(s: _Section, base_dir: Path) -> ReferenceConfig:
    kind = s.string("kind", "step", REFERENCE_KINDS)
    csv_path: Path | None = None
    if kind == "csv":
        rel = s.string("path")
        csv_path = (base_dir / rel).resolve()
        if not csv_path.is_file():
            raise ConfigError(s.name("path"), f"no such CSV file: {csv_path}")
    ref = ReferenceConfig(
        kind=kind,
        position=s.number("position", 1.0),
        start_s=s.number("start_s", 0.0, nonnegative=True),
        amplitude=s.number("amplitude", 1.0),
        frequency_hz=s.number("frequency_hz", 1.0, nonnegative=True),
        offset=s.number("offset", 0.0),
        csv_path=csv_path,
    )
    s.finish()
    return ref


def _parse_run(s: _Section) -> RunConfig:
    run = RunConfig(
        duration_s=s.number("duration_s", 1.0, positive=True),
        dob_enabled=s.boolean("dob_enabled", True),
        log_dir=Path(s.string("log_dir", "logs")),
        missing_feedback_policy=s.string("missing_feedback_policy", "hold", MISSING_FEEDBACK_POLICIES),
        max_missing_periods=s.integer("max_missing_periods", 3, low=0, high=1000),
        sched_fifo=s.boolean("sched_fifo", False),
        cpu_affinity=s.integers("cpu_affinity"),
        freeze_gc=s.boolean("freeze_gc", False),
    )
    s.finish()
    return run
