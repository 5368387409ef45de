"""The TOML configuration: plant, design, drive, simulated drive, reference and run settings.

Parsed as data only (``tomllib``), validated field by field; every problem raises
:class:`~dob_hil.errors.ConfigError` naming the dotted field and what is wrong with it.
Unknown keys are errors too, so a typo never silently falls back to a default. Every key is
declared once in :mod:`dob_hil.config_schema` and read here with ``section.get(key)``
(:mod:`dob_hil.config_reader`); a new key is one ``Field`` line there and one ``get`` here.
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dob_hil.config_reader import Matrix, _Section, _short_int, _short_str
from dob_hil.config_schema import (
    MAX_AUGMENTED_STATES,
    MAX_INPUTS,
    MAX_OUTPUTS,
    MAX_STATES,
)
from dob_hil.errors import ConfigError
from dob_hil.loop.envelope import SafetyConfig, parse_safety

ConfigSection = _Section  # what a profile's parse_options receives: its [drive.<profile>] table

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


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
    ltr_band_hz: tuple[float, float] | None = None  # LTR error band; default up to 2x Gtl's crossover


@dataclass(frozen=True)
class DobConfig:
    """Either an explicit ``Kdist`` or a design method with its parameter."""

    Kdist: Matrix | None = None
    method: str | None = None
    gain: float | None = None


@dataclass(frozen=True)
class OptimizeConfig:
    """``[design.optimize]``: the band and bounds of the ``optimize`` DOB design (dob_hil.design.optimize).
    ``band_hz`` defaults to the span of the sine disturbances in [sim]; ``max_peak_T`` and
    ``max_noise_rms_A`` to the starting design's own values; ``None`` bounds are not imposed."""

    band_hz: tuple[float, float] | None = None
    tune: str = "kdist"
    max_peak_S: float = 2.0
    max_peak_T: float | None = None
    max_noise_rms_A: float | None = None
    max_noise_peak_A: float | None = None
    min_gain_margin_dB: float = 6.0
    min_phase_margin_deg: float = 30.0
    min_disk_gain_margin_dB: float | None = None
    min_disk_phase_margin_deg: float | None = None
    min_delay_margin_samples: float = 1.0


@dataclass(frozen=True)
class DesignConfig:
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    feedback: FeedbackConfig = field(default_factory=FeedbackConfig)
    dob: DobConfig = field(default_factory=DobConfig)
    optimize: OptimizeConfig = field(default_factory=OptimizeConfig)


@dataclass(frozen=True)
class DriveConfig:
    profile: str = "native"
    node_id: int = 1
    node_ids: tuple[int, ...] | None = None  # one per axis (multi-input plants); None: node_id + i
    bitrate_bps: int = 1_000_000
    current_limit_A: float = 0.7
    dac_lsb_A: float = 1.0 / 2048.0
    encoder_counts_per_unit: float = 10000.0
    encoder_bits: int = 32
    watchdog_periods: int = 10
    feedback_timeout_periods: int = 10
    # the profile's own settings, parsed by its descriptor from [drive.<profile>] (None: it has none)
    options: object = None
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
    # [[reference.outputs]]: one command per plant output (empty: output 0 from the keys above)
    outputs: tuple[ReferenceConfig, ...] = ()


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
    log_layout: str = "samples"  # "samples": one message per record; "blocks": runs of records


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
    safety: SafetyConfig = field(default_factory=SafetyConfig)  # [safety]: dob_hil.loop.envelope


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
    where = str(source) if source else "<config>"
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(where, f"not valid TOML: {exc}") from None
    except RecursionError:
        line = _first_line(text, r"[\[{]\s*[\[{]" * 50)
        raise ConfigError(where, f"{line}arrays or tables nested too deep to read") from None
    except ValueError:  # an integer of more than 4300 digits: int() refuses to convert it
        line = _first_line(text, r"[0-9_]{4300}")
        raise ConfigError(where, f"{line}an integer of more than 4300 digits (no key takes one)") from None
    return parse_config(data, source=source, text=text)


def _first_line(text: str, pattern: str) -> str:
    """ "line N: " for the first line matching ``pattern`` (empty if none)."""
    match = re.search(pattern, text)
    return f"line {text.count(chr(10), 0, match.start()) + 1}: " if match else ""


def parse_config(data: Mapping[str, Any], source: Path | None = None, text: str = "") -> Config:
    root = _Section(data, "")
    base_dir = source.parent if source is not None else Path.cwd()
    meta = root.sub("meta")
    name = _parse_name(meta, source)
    meta.get("description")
    meta.finish()
    plant = _parse_plant(root.sub("plant", required=True))
    design = _parse_design(root.sub("design"), plant)
    drive = _parse_drive(root.sub("drive"))
    sim = _parse_sim(root.sub("sim"), plant)
    reference = _parse_reference(root.sub("reference"), base_dir, plant)
    run = _parse_run(root.sub("run"))
    safety = parse_safety(root.sub("safety"))
    root.finish()
    return Config(name, plant, design, drive, sim, reference, run, source, text, safety)


def _parse_name(meta: _Section, source: Path | None) -> str:
    """``meta.name`` becomes a file name: no path separators, no ``..``, nothing hidden."""
    if not meta.has("name"):
        stem = source.stem if source else "config"
        return "".join(c if c.isalnum() or c in "-_." else "_" for c in stem).strip(".") or "config"
    name: str = meta.get("name")
    bad = [c for c in name if not (c.isalnum() or c in " -_.+")]
    if bad or ".." in name or name.startswith((".", " ")) or not name.strip():
        raise ConfigError(
            meta.name("name"),
            "must be a plain name (letters, digits, space, - _ . +; no path separators or '..'); "
            f"got {_short_str(name)}",
        )
    return name


def _parse_plant(s: _Section) -> PlantConfig:
    A: Matrix = s.get("A")
    if A.shape[0] != A.shape[1]:
        raise ConfigError(s.name("A"), f"must be square, got {A.shape[0]}x{A.shape[1]}")
    n = A.shape[0]
    if n > MAX_STATES:
        raise ConfigError(s.name("A"), f"{n} states; the design handles at most {MAX_STATES}")
    B: Matrix = s.get("B")
    if B.shape[0] == 1 and B.shape[1] == n and n != 1:
        B = B.T  # a flat list where a column is meant: ``B = [0.0, 2.1484e4]``
    if B.shape[0] != n:
        raise ConfigError(s.name("B"), f"must have {n} rows (A is {n}x{n}), got {B.shape[0]}")
    if B.shape[1] > MAX_INPUTS:
        raise ConfigError(s.name("B"), f"{B.shape[1]} inputs; the design handles at most {MAX_INPUTS}")
    C: Matrix = s.get("C", (None, n), f"A is {n}x{n}")
    if C.shape[0] > MAX_OUTPUTS:
        raise ConfigError(s.name("C"), f"{C.shape[0]} outputs; the design handles at most {MAX_OUTPUTS}")
    period_us: float = s.get("period_us")
    period_ns = round(period_us * 1000.0)
    if period_ns <= 0 or abs(period_ns - period_us * 1000.0) > 1e-6 * max(1.0, period_us):
        raise ConfigError(s.name("period_us"), f"must be a whole number of ns, got {period_us} us")
    delay: int = s.get("input_delay_samples")
    m = B.shape[1]
    if n + delay * m > MAX_AUGMENTED_STATES:
        raise ConfigError(
            s.name("input_delay_samples"),
            f"{delay} samples x {m} inputs + {n} states = {n + delay * m} augmented states; "
            f"the design handles at most {MAX_AUGMENTED_STATES}",
        )
    state_names = s.get("state_names") or tuple(f"x{i + 1}" for i in range(n))
    input_names = s.get("input_names") or tuple(f"u{i + 1}" for i in range(m))
    output_names = s.get("output_names") or tuple(f"y{i + 1}" for i in range(C.shape[0]))
    for key, names, count in (
        ("state_names", state_names, n),
        ("input_names", input_names, m),
        ("output_names", output_names, C.shape[0]),
    ):
        if len(names) != count:
            raise ConfigError(s.name(key), f"expected {count} names, got {len(names)}")
    input_unit: str = s.get("input_unit")
    output_unit: str = s.get("output_unit")
    for key, values in (
        ("state_names", state_names),
        ("input_names", input_names),
        ("output_names", output_names),
        ("input_unit", (input_unit,)),
        ("output_unit", (output_unit,)),
    ):
        for value in values:
            if "$" in value:  # plot labels would parse it as mathtext ("$\frac{$" crashes it)
                raise ConfigError(
                    s.name(key), f"contains '$' (plot labels read it as math); got {_short_str(value)}"
                )
    s.finish()
    return PlantConfig(
        A, B, C, period_ns, delay, state_names, input_names, output_names, input_unit, output_unit
    )


def _gain(s: _Section, key: str, shape: tuple[int | None, int | None], why: str) -> Matrix | None:
    """A design matrix of the schema, shaped against the plant (the error says why)."""
    arr: Matrix | None = s.get(key, shape, why)
    return arr


def _parse_design(s: _Section, plant: PlantConfig) -> DesignConfig:
    n_aug = plant.n_states + plant.input_delay_samples * plant.n_inputs
    p, m = plant.n_outputs, plant.n_inputs
    if plant.input_delay_samples:
        aug = f"{plant.n_states} states + {plant.input_delay_samples} delay samples x {m} inputs = {n_aug}"
    else:
        aug = f"{n_aug} states"
    e = s.sub("estimator")
    est = EstimatorConfig(
        Lc=_gain(e, "Lc", (n_aug, p), f"augmented states x outputs: {aug}, {p} outputs"),
        Gam1=_gain(e, "Gam1", (n_aug, None), f"augmented states x k: {aug}"),
        D1=_gain(e, "D1", (p, None), f"outputs x l: {p} outputs"),
    )
    if est.Lc is not None and (est.Gam1 is not None or est.D1 is not None):
        raise ConfigError(e.name("Lc"), "give either Lc or the DARE weights Gam1/D1, not both")
    e.finish()
    f = s.sub("feedback")
    fb = FeedbackConfig(
        Kc=_gain(f, "Kc", (m, n_aug), f"inputs x augmented states: {m} inputs, {aug}"),
        q=f.get("q"),
        R2=_gain(f, "R2", (m, m), f"inputs x inputs: {m} inputs"),
        ltr_q_values=f.get("ltr_q_values"),
        ltr_band_hz=_band_hz(f, "ltr_band_hz"),
    )
    if fb.Kc is not None and (fb.q is not None or fb.R2 is not None):
        raise ConfigError(f.name("Kc"), "give either Kc or the LTR weights q/R2, not both")
    f.finish()
    d = s.sub("dob")
    dob = DobConfig(
        Kdist=_gain(d, "Kdist", (m, n_aug), f"inputs x augmented states: {m} inputs, {aug}"),
        method=d.get("method") or None,
        gain=d.get("gain"),
    )
    if dob.Kdist is not None and dob.method is not None:
        raise ConfigError(d.name("Kdist"), "give either Kdist or a design method, not both")
    d.finish()
    opt = _parse_optimize(s.sub("optimize"))
    s.finish()
    return DesignConfig(est, fb, dob, opt)


def _band_hz(s: _Section, key: str) -> tuple[float, float] | None:
    band: tuple[float, ...] | None = s.get(key)
    if band is not None and (len(band) != 2 or band[0] > band[1]):
        raise ConfigError(s.name(key), f"must be [lo, hi] in Hz with lo <= hi, got {list(band)}")
    return (band[0], band[1]) if band is not None else None


def _parse_optimize(o: _Section) -> OptimizeConfig:
    cfg = OptimizeConfig(
        band_hz=_band_hz(o, "band_hz"),
        tune=o.get("tune"),
        max_peak_S=o.get("max_peak_S"),
        max_peak_T=o.get("max_peak_T"),
        max_noise_rms_A=o.get("max_noise_rms_A"),
        max_noise_peak_A=o.get("max_noise_peak_A"),
        min_gain_margin_dB=o.get("min_gain_margin_dB"),
        min_phase_margin_deg=o.get("min_phase_margin_deg"),
        min_disk_gain_margin_dB=o.get("min_disk_gain_margin_dB"),
        min_disk_phase_margin_deg=o.get("min_disk_phase_margin_deg"),
        min_delay_margin_samples=o.get("min_delay_margin_samples"),
    )
    o.finish()
    return cfg


def _parse_drive(s: _Section) -> DriveConfig:
    from dob_hil.profiles import get_profile

    profile = get_profile(s.get("profile"))
    options = None
    if profile.parse_options is not None:
        sub = s.sub(profile.name)
        options = profile.parse_options(sub)
        sub.finish()
    d = DriveConfig(profile=profile.name, options=options, **s.get_all(skip=("profile",)))
    if d.current_limit_A / d.dac_lsb_A > 32767:
        raise ConfigError(
            s.name("current_limit_A"),
            f"{d.current_limit_A} A is {d.current_limit_A / d.dac_lsb_A:.0f} DAC LSBs; "
            "the int16 current command holds at most 32767",
        )
    if d.current_limit_A < d.dac_lsb_A:
        raise ConfigError(s.name("current_limit_A"), "is smaller than one DAC LSB")
    if d.node_ids is not None and len(set(d.node_ids)) != len(d.node_ids):
        raise ConfigError(s.name("node_ids"), f"must be distinct, got {list(d.node_ids)}")
    s.finish()
    return d


def _parse_sim(s: _Section, plant: PlantConfig) -> SimConfig:
    dists: list[DisturbanceConfig] = []
    s._ask("disturbance")
    if s.has("disturbance"):
        raw = s.raw("disturbance")
        if not isinstance(raw, list):
            raise ConfigError(s.name("disturbance"), "expected an array of tables [[sim.disturbance]]")
        for i, item in enumerate(raw):
            ds = _Section(item, f"{s.name('disturbance')}[{i}]")
            dists.append(DisturbanceConfig(**ds.get_all()))
            if dists[-1].input_index > plant.n_inputs - 1:
                raise ConfigError(
                    ds.name("input_index"),
                    f"must be <= {plant.n_inputs - 1} (the plant has {plant.n_inputs} inputs), "
                    f"got {dists[-1].input_index}",
                )
            ds.finish()
    init: tuple[float, ...] | None = s.get("initial_state")
    if init is not None and len(init) != plant.n_states:
        raise ConfigError(s.name("initial_state"), f"expected {plant.n_states} values, got {len(init)}")
    sim = SimConfig(
        **s.get_all(skip=("initial_state",)),
        initial_state=init,
        disturbances=tuple(dists),
        faults=_parse_faults(s.sub("faults")),
    )
    s.finish()
    return sim


def _parse_faults(s: _Section) -> FaultsConfig:
    faults = FaultsConfig(**s.get_all())
    if faults.encoder_jump_at_s is not None and faults.encoder_jump_counts == 0:
        raise ConfigError(s.name("encoder_jump_counts"), "missing or 0: give the jump's size in counts")
    s.finish()
    return faults


def _parse_reference(s: _Section, base_dir: Path, plant: PlantConfig) -> ReferenceConfig:
    """``[reference]`` (output 0) or ``[[reference.outputs]]`` (one table per output), not both."""
    s._ask("outputs")
    if not s.has("outputs"):
        return _parse_one_reference(s, base_dir, plant)
    raw = s.raw("outputs")
    if not isinstance(raw, list):
        raise ConfigError(s.name("outputs"), "expected an array of tables [[reference.outputs]]")
    if len(raw) != plant.n_outputs:
        raise ConfigError(
            s.name("outputs"),
            f"expected {plant.n_outputs} tables, one per plant output (the plant has "
            f"{plant.n_outputs} outputs), got {len(raw)}",
        )
    default = ReferenceConfig()
    for key in ("kind", "position", "start_s", "amplitude", "frequency_hz", "offset", "path"):
        if s.has(key) and (key == "path" or s.get(key) != getattr(default, key)):
            raise ConfigError(
                s.name(key),
                f"give either {s.name('outputs')} (one table per output) or the single-output "
                f"{s.name(key)}, not both",
            )
    outputs = tuple(
        _parse_one_reference(_Section(item, f"{s.name('outputs')}[{i}]"), base_dir, plant)
        for i, item in enumerate(raw)
    )
    s.finish()
    return ReferenceConfig(outputs=outputs)


def _parse_one_reference(s: _Section, base_dir: Path, plant: PlantConfig) -> ReferenceConfig:
    kind: str = s.get("kind")
    csv_path: Path | None = None
    rel: str | None = s.get("path")
    if kind == "csv":
        if rel is None:
            raise ConfigError(s.name("path"), "missing (a required string with kind = 'csv')")
        csv_path = (base_dir / rel).resolve()
        if not csv_path.is_file():
            raise ConfigError(s.name("path"), f"no such CSV file: {csv_path}")
        from dob_hil.control.reference import read_reference_csv

        read_reference_csv(csv_path, s.name("path"))  # every row checked before anything runs
    ref = ReferenceConfig(
        kind=kind,
        position=s.get("position"),
        start_s=s.get("start_s"),
        amplitude=s.get("amplitude"),
        frequency_hz=s.get("frequency_hz"),
        offset=s.get("offset"),
        csv_path=csv_path,
    )
    nyquist_hz = 0.5e9 / plant.period_ns
    if kind == "sine" and ref.frequency_hz >= nyquist_hz:
        raise ConfigError(
            s.name("frequency_hz"),
            f"must be below the Nyquist frequency {nyquist_hz:g} Hz of the {plant.period_ns / 1000:g} us "
            f"period, got {ref.frequency_hz:g}",
        )
    s.finish()
    return ref


def check_value(section: str, key: str, value: object, name: str) -> Any:
    """A value given elsewhere (a command-line option ``name``) checked against the schema field
    ``section.key``; the ConfigError names ``name``."""
    try:
        return _Section({key: value}, section).get(key)
    except ConfigError as exc:
        raise ConfigError(name, exc.problem) from None


def usable_cpus() -> set[int]:
    """The CPUs this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return set(os.sched_getaffinity(0))
    return set(range(os.cpu_count() or 1))  # pragma: no cover


def check_cpus(cpus: Sequence[int], field_name: str) -> None:
    """Each CPU must be one this process may use; ConfigError on ``field_name`` otherwise."""
    allowed = usable_cpus()
    for cpu in cpus:
        if cpu not in allowed:
            raise ConfigError(
                field_name,
                f"CPU {_short_int(cpu)} is not one this process may use (allowed: "
                f"{', '.join(str(c) for c in sorted(allowed))})",
            )


def _parse_run(s: _Section) -> RunConfig:
    run = RunConfig(**s.get_all(skip=("log_dir",)), log_dir=Path(s.get("log_dir")))
    s.finish()
    return run
