"""The config schema: every key of every section with its type, unit, default, range and meaning.

One table, used three ways: :mod:`dob_hil.config` parses and validates each key through its
:class:`Field` (type, bounds, choices, the "did you mean" list of valid keys), ``docs/CONFIG.md``'s
reference part is rendered from it (:mod:`dob_hil.config_doc`, checked by a test) and
``dob-hil config --template`` writes a commented starter config from it.

Adding a key is one :class:`Field` line in its section below plus the dataclass field of the same
name in :mod:`dob_hil.config` (``[drive]``, ``[sim]``, ``[[sim.disturbance]]``, ``[sim.faults]`` and
``[run]`` pass every schema key to their dataclass with ``section.get_all()``; the others read
each key with ``section.get("key")``). A new table is one :class:`SectionSpec`. The doc
(``python3 tools/config_doc.py``), the template and the unknown-key hints follow on their own.

Bounds are physical sanity limits, chosen so that no accepted value can overflow a float or an
integer conversion during a run (a time of 1e308 s, a 1e308 A disturbance): far outside any real
servo, well inside float64. Matrices have a size bound so that the design stays interactive.
"""

from __future__ import annotations

from dataclasses import dataclass

# Size bounds of the design problem (the design's DAREs and root loci grow as the cube of the
# augmented state count; a 300-state plant took minutes): checked when the plant is parsed.
MAX_STATES = 24
MAX_INPUTS = 6
MAX_OUTPUTS = 6
MAX_DELAY_SAMPLES = 20
MAX_AUGMENTED_STATES = 48  # states + input_delay_samples * inputs
MAX_MATRIX_ENTRY = 1e12  # |entry| of any matrix (plant, gains, weights)
MAX_TIME_S = 1e6  # any time or duration in seconds (11.6 days)
MAX_STRING_CHARS = 200

REQUIRED = "<required>"  # the default of a field that must be given

MISSING_FEEDBACK_POLICIES = ("hold", "extrapolate", "zero")
REFERENCE_KINDS = ("step", "sine", "csv")
DISTURBANCE_KINDS = ("sine", "step", "noise")
OPTIMIZE_TUNES = ("kdist", "all")


@dataclass(frozen=True)
class Field:
    """One key. ``kind``: number, integer, boolean, string, strings, integers, numbers, matrix.

    ``default``: the value used when the key is absent; :data:`REQUIRED` if it must be given;
    None if absent means "not set" (e.g. give either ``Lc`` or ``Gam1``/``D1``).
    Bounds: ``low``/``high`` inclusive, ``low_open``/``high_open`` make them exclusive; for
    ``numbers`` and ``matrix`` they bound every entry's magnitude (``high``) or value (``low``).
    ``shape``: the matrix shape in words, for the doc. ``example``: TOML text for the template
    (defaults to the default).
    """

    key: str
    kind: str
    doc: str
    unit: str = ""
    default: object = None
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    choices: tuple[str, ...] = ()
    shape: str = ""
    example: str = ""

    def range_text(self) -> str:
        if self.choices:
            return " | ".join(self.choices)
        if self.kind == "matrix":
            return f"|entry| <= {self.high:g}" if self.high is not None else ""
        lo = "" if self.low is None else f"{'>' if self.low_open else '>='} {_num(self.low)}"
        hi = "" if self.high is None else f"{'<' if self.high_open else '<='} {_num(self.high)}"
        text = ", ".join(t for t in (lo, hi) if t)
        if self.kind in ("numbers",) and text:
            return f"each {text}"
        return text


def _num(x: float) -> str:
    if float(x).is_integer() and abs(x) < 1e7:
        return str(int(x))
    return f"{x:g}"


@dataclass(frozen=True)
class SectionSpec:
    """One TOML table. ``path`` is dotted; an array of tables ends in ``[]``."""

    path: str
    doc: str
    fields: tuple[Field, ...]

    def field(self, key: str) -> Field:
        for f in self.fields:
            if f.key == key:
                return f
        raise KeyError(f"{self.path}.{key} is not in the config schema")

    @property
    def keys(self) -> tuple[str, ...]:
        return tuple(f.key for f in self.fields)


def _f(key: str, kind: str, doc: str, **kw: object) -> Field:
    return Field(key, kind, doc, **kw)  # type: ignore[arg-type]


_M = MAX_MATRIX_ENTRY
_T = MAX_TIME_S

# fmt: off
_REFERENCE_FIELDS: tuple[Field, ...] = (
    _f("kind", "string", "`step`, `sine` or `csv`.", default="step", choices=REFERENCE_KINDS),
    _f("position", "number", "Step: target position.", unit="output unit", default=1.0,
       low=-1e6, high=1e6),
    _f("start_s", "number", "Step: time of the step.", unit="s", default=0.0, low=0.0, high=_T),
    _f("amplitude", "number", "Sine: amplitude.", unit="output unit", default=1.0, low=-1e6,
       high=1e6),
    _f("frequency_hz", "number", "Sine: frequency, below the Nyquist frequency 1/(2 period).",
       unit="Hz", default=1.0, low=0.0, high=1e6),
    _f("offset", "number", "Sine: offset.", unit="output unit", default=0.0, low=-1e6,
       high=1e6),
    _f("path", "string", "CSV: a UTF-8 file, relative to the config, with the header "
       "`time_s,position` or `time_s,position,velocity`, times increasing; interpolated "
       "linearly, held after its last row. Required with kind = csv."),
)

SCHEMA: tuple[SectionSpec, ...] = (
    SectionSpec("meta", "What the config is called.", (
        _f("name", "string", "Name of the run: the default log file name and the plots' titles. "
           "Letters, digits, space, `-`, `_`, `.`, `+`; no path separators or `..`.",
           default="the file name's stem", example='"my-motor"'),
        _f("description", "string", "Free text, kept in the log's copy of the config.", default=""),
    )),
    SectionSpec("plant", "The continuous-time plant dx/dt = A x + B u, y = C x, sampled with a "
                "zero-order hold every `period_us`. n states, m inputs, p outputs. Flat lists are "
                "columns where a column is meant (`B = [0, 2.1e4]` is 2x1).", (
        _f("A", "matrix", "Continuous state matrix.", unit="1/s", shape="n x n", default=REQUIRED,
           high=_M, example="[[0.0, 1.0], [0.0, -128.59]]"),
        _f("B", "matrix", "Continuous input matrix (inputs in `input_unit`).",
           unit="state unit/s per input unit", shape="n x m", default=REQUIRED, high=_M,
           example="[0.0, 2.1484e4]"),
        _f("C", "matrix", "Output matrix: what the drive measures (the encoder position).",
           shape="p x n", default=REQUIRED, high=_M, example="[[1.0, 0.0]]"),
        _f("period_us", "number", "Control period: the drive samples and the controller answers "
           "once per period. A whole number of nanoseconds.", unit="us", default=REQUIRED,
           low=0.0, low_open=True, high=1e6, example="300.0"),
        _f("input_delay_samples", "integer", "Whole samples of input delay (computation, bus) that "
           "the design models by augmenting the plant to n_aug = n + delay x m states "
           f"(at most {MAX_AUGMENTED_STATES}).", unit="samples", default=0, low=0,
           high=MAX_DELAY_SAMPLES),
        _f("state_names", "strings", "One name per state, for logs and plots.",
           default="x1, x2, ...", example='["position", "velocity"]'),
        _f("input_names", "strings", "One name per input.", default="u1, ...",
           example='["current"]'),
        _f("output_names", "strings", "One name per output.", default="y1, ...",
           example='["position"]'),
        _f("input_unit", "string", "Unit of the inputs, for labels.", default="A"),
        _f("output_unit", "string", "Unit of the outputs (and of the position states), for labels.",
           default="unit", example='"rev"'),
    )),
    SectionSpec("design.estimator", "The current estimator's gain: give `Lc`, or leave it out and "
                "the Kalman DARE (paper eq. 6-7) designs it from the weights `Gam1` and `D1`.", (
        _f("Lc", "matrix", "Estimator gain.", shape="n_aug x p", high=_M, example="[0.75, 0.5]"),
        _f("Gam1", "matrix", "Process-noise input of the estimator DARE; larger entries: a faster "
           "estimator that trusts the measurement more.", shape="n_aug x k", high=_M,
           default="Gam_w (noise enters at the plant input)"),
        _f("D1", "matrix", "Measurement-noise weight of the estimator DARE.", shape="p x l",
           high=_M, default="identity"),
    )),
    SectionSpec("design.feedback", "The state feedback gain: give `Kc`, or leave it out and the "
                "loop-transfer-recovery DARE designs it from `q` (R1 = q C'C) and `R2`.", (
        _f("Kc", "matrix", "State feedback gain.", shape="m x n_aug", high=_M,
           example="[[107.42, 0.3]]"),
        _f("q", "number", "LTR weight: R1 = q C'C; larger q: a faster loop, closer to the "
           "estimator loop's robustness.", low=0.0, low_open=True, high=_M, default="1"),
        _f("R2", "matrix", "Input weight of the LTR DARE; larger: gentler commands.", shape="m x m",
           high=_M, default="identity"),
        _f("ltr_q_values", "numbers", "q values of the LTR table and plot of `dob-hil design`; "
           "extended by decades until the loop recovers the target in `ltr_band_hz`.",
           low=0.0, low_open=True, high=_M, example="[1.0, 100.0, 1.0e4, 1.0e6]"),
        _f("ltr_band_hz", "numbers", "[lo, hi]: the band in which the LTR error is measured.",
           unit="Hz", low=0.0, low_open=True, high=1e9,
           default="lowest plotted frequency to twice the target loop's crossover",
           example="[0.1, 200.0]"),
    )),
    SectionSpec("design.dob", "The disturbance observer gain: give `Kdist`, or leave it out and "
                "`method` designs it.", (
        _f("Kdist", "matrix", "Disturbance observer gain.", shape="m x n_aug", high=_M,
           example="[[18.0, 3.75]]"),
        _f("method", "string", "Design method of Kdist: `dc_loop_gain` (DOB loop DC gain = "
           "`gain`, default 1, i.e. 50 % of a constant disturbance estimated; the default method), "
           "`dc_estimate` (estimates the fraction `gain` of a constant disturbance, default 0.8), "
           "`stable_fraction` (`gain` in (0, 1) of the stable range, default 0.25), `min_radius` "
           "(the fastest estimate among gains estimating at least `gain` of a constant "
           "disturbance, default 0.5) or `optimize` (best rejection within the bounds of "
           "[design.optimize]).", default=""),
        _f("gain", "number", "Parameter of the design method.", low=0.0, low_open=True, high=_M,
           default="per method"),
    )),
    SectionSpec("design.optimize", "The `optimize` DOB design (`design.dob.method = \"optimize\"` "
                "or `dob-hil design --optimize`): the best worst-case disturbance rejection over "
                "`band_hz` subject to the bounds below.", (
        _f("band_hz", "numbers", "[lo, hi]: the band whose worst rejection |y/w| is minimised.",
           unit="Hz", low=0.0, low_open=True, high=1e9,
           default="the span of the sine disturbances in [sim]", example="[4.0, 12.0]"),
        _f("tune", "string", "What is chosen: `kdist` (Kdist only) or `all` (Lc, Kc and Kdist, "
           "directly, starting from the config's gains).", default="kdist",
           choices=OPTIMIZE_TUNES),
        _f("max_peak_S", "number", "Bound on peak |S| (sigma_max) at the plant output.",
           default=2.0, low=1.0, high=1e3),
        _f("max_peak_T", "number", "Bound on peak |T| at the plant output.", low=0.0,
           low_open=True, high=1e3, default="the starting design's"),
        _f("max_noise_rms_A", "number", "Bound on the RMS current from white encoder noise of one "
           "count RMS.", unit="A", low=0.0, low_open=True, high=1e6, default="the starting design's"),
        _f("max_noise_peak_A", "number", "Bound on the current from one count of encoder noise at "
           "the worst frequency.", unit="A", low=0.0, low_open=True, high=1e6, default="none"),
        _f("min_gain_margin_dB", "number", "Bound on the gain margin (loop at a time, plant input).",
           unit="dB", default=6.0, low=0.0, high=200.0),
        _f("min_phase_margin_deg", "number", "Bound on the phase margin (loop at a time, plant "
           "input).", unit="deg", default=30.0, low=0.0, high=180.0),
        _f("min_disk_gain_margin_dB", "number", "Bound on the balanced disk gain margin "
           "(optimiser constraint and warning bound; for several inputs also on the multiloop margin "
           "at the plant input).", unit="dB", low=0.0, low_open=True, high=200.0,
           default="none (warning bound 6 dB for several inputs)"),
        _f("min_disk_phase_margin_deg", "number", "Bound on the balanced disk phase "
           "margin (optimiser constraint and warning bound; for several inputs also on the multiloop "
           "margin at the plant input).", unit="deg", low=0.0, low_open=True, high=90.0,
           default="none (warning bound 30 deg for several inputs)"),
        _f("min_delay_margin_samples", "number", "Bound on the delay margin.", unit="samples",
           default=1.0, low=0.0, high=1e6),
    )),
    SectionSpec("drive", "The drive and its wire format. `[drive.<profile>]` holds the profile's "
                "own options, if it has any.", (
        _f("profile", "string", "Drive profile: wire format and simulated counterpart.",
           default="native"),
        _f("node_id", "integer", "CAN node id of the drive.", default=1, low=0, high=127),
        _f("bitrate_bps", "integer", "CAN bitrate, for the bus-load check.", unit="bit/s",
           default=1_000_000, low=10_000, high=8_000_000),
        _f("current_limit_A", "number", "Largest current ever commanded; at most 32767 DAC LSBs.",
           unit="A", default=0.7, low=0.0, low_open=True, high=1000.0),
        _f("dac_lsb_A", "number", "Current of one DAC code: the command's resolution.", unit="A",
           default=1.0 / 2048.0, low=0.0, low_open=True, high=1.0, example="0.00048828125"),
        _f("encoder_counts_per_unit", "number", "Encoder counts per `output_unit`.",
           unit="counts/unit", default=10000.0, low=0.01, high=1e9),
        _f("encoder_bits", "integer", "Width of the encoder counter (it wraps).", unit="bits",
           default=32, low=8, high=32),
        _f("watchdog_periods", "integer", "The drive disables itself after this many periods "
           "without a command.", unit="periods", default=10, low=1, high=100_000),
        _f("feedback_timeout_periods", "integer", "The host stops the run after this many periods "
           "without feedback.", unit="periods", default=10, low=1, high=100_000),
        _f("clear_fault", "boolean", "Clear a fault the drive reports (e.g. one left by a killed "
           "run) before enabling; `dob-hil run --clear-fault` sets it.", default=False),
        _f("node_ids", "integers", "Several axes (a plant with N > 1 inputs, one per output): "
           "the CAN node id of each axis, distinct, axis i = input i and output i (native: "
           "0..15).", low=0, high=127, default="node_id + i"),
    )),
    SectionSpec("sim", "The simulated drive (`firmware_sim`): plant integration and impairments.", (
        _f("substeps", "integer", "Integration substeps per period (ground-truth resolution).",
           default=10, low=1, high=10_000),
        _f("noise_counts_std", "number", "Standard deviation of the encoder noise.", unit="counts",
           default=0.0, low=0.0, high=1e6),
        _f("seed", "integer", "Seed of the noise and loss generators.", default=0, low=0,
           high=2**63 - 1),
        _f("latency_us", "number", "Real time only: delay before the drive sends its feedback.",
           unit="us", default=0.0, low=0.0, high=1e6),
        _f("jitter_us", "number", "Real time only: uniform random extra delay, 0 .. jitter.",
           unit="us", default=0.0, low=0.0, high=1e6),
        _f("loss_probability", "number", "Probability that a feedback frame is dropped.",
           default=0.0, low=0.0, high=1.0, high_open=True),
        _f("initial_state", "numbers", "Plant state at enable, one value per state.",
           unit="state units", high=1e6, default="zeros"),
    )),
    SectionSpec("sim.disturbance[]", "`[[sim.disturbance]]`, repeatable: a current the simulated "
                "drive adds at a plant input.", (
        _f("kind", "string", "`sine` (amplitude, frequency, phase), `step` (amplitude from "
           "`start_s` on) or `noise` (white, `std_A`).", default=REQUIRED,
           choices=DISTURBANCE_KINDS, example='"sine"'),
        _f("amplitude_A", "number", "Amplitude (sine, step).", unit="A", default=0.0, low=-1e4,
           high=1e4, example="0.2"),
        _f("frequency_hz", "number", "Frequency (sine).", unit="Hz", default=0.0, low=0.0,
           high=1e6, example="4.0"),
        _f("phase_rad", "number", "Phase (sine).", unit="rad", default=0.0, low=-1e3, high=1e3),
        _f("start_s", "number", "Time the disturbance starts.", unit="s", default=0.0, low=0.0,
           high=_T),
        _f("std_A", "number", "Standard deviation (noise).", unit="A", default=0.0, low=0.0,
           high=1e4),
        _f("seed", "integer", "Seed (noise).", default=0, low=0, high=2**63 - 1),
        _f("input_index", "integer", "The plant input it is added to, 0-based (< m).", default=0,
           low=0),
    )),
    SectionSpec("sim.faults", "Faults the simulated drive injects on its own, at a time after its "
                "first enable (rounded to whole periods, at least one).", (
        _f("fault_at_s", "number", "The drive enters FAULT (over-current).", unit="s", low=0.0,
           low_open=True, high=_T),
        _f("silent_at_s", "number", "The drive stops sending (it still acts on commands).",
           unit="s", low=0.0, low_open=True, high=_T),
        _f("encoder_jump_at_s", "number", "The encoder counter steps by `encoder_jump_counts`.",
           unit="s", low=0.0, low_open=True, high=_T),
        _f("encoder_jump_counts", "integer", "Size of the encoder jump (required with its time).",
           unit="counts", default=0, low=-(2**31), high=2**31 - 1),
    )),
    SectionSpec("reference", "The commanded output 0 (the other outputs are held at zero). For the "
                "paper's plant (position, velocity) the reference state is [position, velocity]; "
                "in general x_ref = Nx r + Nv r' with the plant's steady-state map. To command "
                "every output, give `[[reference.outputs]]` instead.", _REFERENCE_FIELDS),
    SectionSpec("reference.outputs[]", "`[[reference.outputs]]`, one table per plant output, in "
                "output order (exactly as many as the plant has outputs): each output's command, "
                "with the keys of `[reference]` (which then keeps its defaults).",
                _REFERENCE_FIELDS),
    SectionSpec("run", "The run.", (
        _f("duration_s", "number", "Run length (`--duration` overrides it).", unit="s",
           default=1.0, low=0.0, low_open=True, high=_T),
        _f("dob_enabled", "boolean", "Disturbance observer on (`--no-dob` switches it off).",
           default=True),
        _f("log_dir", "string", "Folder of the default log path "
           "`<log_dir>/<name>-<dob|nodob>-<UTC time>.mcap`.", default="logs"),
        _f("missing_feedback_policy", "string", "What the controller uses for a period without "
           "feedback.", default="hold", choices=MISSING_FEEDBACK_POLICIES),
        _f("max_missing_periods", "integer", "Consecutive periods without feedback the policy "
           "bridges; beyond, the command is zero.", unit="periods", default=3, low=0, high=1000),
        _f("sched_fifo", "boolean", "Real time: run the loop under SCHED_FIFO where permitted.",
           default=False),
        _f("cpu_affinity", "integers", "Real time: CPUs to pin the loop to; `dob-hil run` checks "
           "that each is one it may use on the machine it runs on.", low=0, high=4095),
        _f("freeze_gc", "boolean", "Real time: gc.freeze() and gc.disable() during the run.",
           default=False),
        _f("log_layout", "string", "MCAP messages of the log (`--log-layout` overrides it): "
           "`samples`, one message per sample, frame and truth record (Foxglove plots every field "
           "against time); `blocks`, one message per run of records of a channel (about 40 % "
           "smaller; Foxglove shows arrays). dob-hil reads both alike.", default="samples",
           choices=("samples", "blocks")),
    )),
    SectionSpec("safety", "A safety envelope: crossing any bound stops the run safely (zero current, "
                "drive disabled) with a non-zero exit naming the bound. A non-finite position always "
                "trips.", (
        _f("max_abs_position", "number", "Largest |measured output|.", unit="output unit", low=0.0,
           low_open=True),
        _f("position_window", "numbers", "Allowed [low, high] of the measured output.",
           unit="output unit", example="[-2.0, 2.0]"),
        _f("max_abs_velocity", "number", "Largest |estimated output velocity| (default: the speed at "
           "which the encoder moves a quarter of its range per period).", unit="output unit/s",
           low=0.0, low_open=True),
        _f("max_tracking_error", "number", "Largest |reference - measured output|.",
           unit="output unit", low=0.0, low_open=True),
        _f("max_encoder_jumps", "integer", "Encoder-jump events tolerated before a trip.", default=0,
           low=0, high=1_000_000_000),
    )),
)
# fmt: on

_BY_PATH = {s.path: s for s in SCHEMA}


def section_spec(path: str) -> SectionSpec | None:
    """The spec of a dotted section path (``sim.disturbance[3]`` finds ``sim.disturbance[]``)."""
    if path.endswith("]") and "[" in path:
        path = path[: path.rindex("[")] + "[]"
    return _BY_PATH.get(path)


def subsections(path: str) -> tuple[str, ...]:
    """Names of the tables directly inside ``path`` ("" for the root)."""
    prefix = f"{path}." if path else ""
    names: list[str] = []
    for spec in SCHEMA:
        p = spec.path.removesuffix("[]")
        if p.startswith(prefix):
            head = p[len(prefix) :].split(".")[0]
            if head not in names:
                names.append(head)
    return tuple(names)
