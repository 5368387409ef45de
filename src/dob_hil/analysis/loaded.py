"""A log read back and interpreted: the arrays plus what the attachments and metadata say.

:func:`load_log` reads the MCAP file (:func:`dob_hil.log.read_log`, vectorised) and parses the
design (``design.json`` attachment) and the config (``config.toml`` attachment) that the run used.
Nothing here raises for a damaged or incomplete log except a file that is no log at all
(:class:`~dob_hil.errors.LogReadError`): whatever cannot be recovered becomes a warning naming
what is lost, and the fields that depend on it are None.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import numpy as np

from dob_hil.config import Config, parse_config_text
from dob_hil.design import Design
from dob_hil.errors import DobHilError
from dob_hil.log import LogData, read_log
from dob_hil.log.reader import StructArray
from dob_hil.log.schemas import FLAG_DOB_ON, TOPIC_CAN, TOPIC_SAMPLE, TOPIC_TRUTH

DESIGN_ATTACHMENT = "design.json"
CONFIG_ATTACHMENT = "config.toml"


@dataclass
class LoadedLog:
    """One log and its interpretation. ``warnings`` holds the reader's and this module's."""

    path: Path
    data: LogData
    design: Design | None
    config: Config | None
    period_ns: int
    dob_enabled: bool
    mode: str  # "lockstep", "realtime" or "unknown"
    bitrate_bps: int | None
    warnings: list[str] = field(default_factory=list)

    @property
    def label(self) -> str:
        """A short column title: the file stem and the DOB state."""
        return f"{self.path.stem} (DOB {'on' if self.dob_enabled else 'off'})"

    @property
    def run(self) -> dict[str, str]:
        return self.data.metadata.get("run", {})

    @property
    def summary(self) -> dict[str, str]:
        return self.data.metadata.get("summary", {})

    @property
    def scenario(self) -> str:
        if "scenario" in self.run:
            return self.run["scenario"]
        return self.design.name if self.design is not None else "?"

    @property
    def current_limit_A(self) -> float | None:
        """The drive's configured current limit (config, else run metadata)."""
        if self.config is not None:
            return self.config.drive.current_limit_A
        return _float_or_none(self.run.get("current_limit_A"))


def _float_or_none(text: str | None) -> float | None:
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        return None
    return value if np.isfinite(value) else None


def _int_or_none(text: str | None) -> int | None:
    value = _float_or_none(text)
    if value is None or value <= 0 or value != int(value):
        return None
    return int(value)


def _one_line(exc: BaseException, limit: int = 200) -> str:
    """An exception as one short line (a hostile attachment's text never floods the terminal)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    if isinstance(exc, RecursionError):
        text = "nested too deeply"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _design_of(data: LogData, warnings: list[str]) -> Design | None:
    blob = data.attachments.get(DESIGN_ATTACHMENT)
    if blob is None:
        warnings.append(f"no {DESIGN_ATTACHMENT} attachment: model output, S/T and replay unavailable")
        return None
    try:
        design = Design.from_json(blob.decode("utf-8"))
    except (ValueError, ArithmeticError, RecursionError, TypeError, LookupError, DobHilError) as exc:
        # UnicodeDecodeError, JSON errors and integers over 4300 digits are ValueErrors; huge
        # integers overflow floats; deep nesting exhausts the recursion limit
        reason = _one_line(exc)
        warnings.append(
            f"{DESIGN_ATTACHMENT} attachment unusable ({reason}): model output and S/T unavailable"
        )
        return None
    layout = data.layout
    if (design.n_states, design.n_inputs, design.n_outputs) != (
        layout.n_states,
        layout.n_inputs,
        layout.n_outputs,
    ):
        warnings.append(
            f"{DESIGN_ATTACHMENT}: dimensions {design.n_states}/{design.n_inputs}/{design.n_outputs} "
            f"do not match the log's {layout.n_states}/{layout.n_inputs}/{layout.n_outputs}; ignored"
        )
        return None
    return design


def _config_of(data: LogData, warnings: list[str]) -> Config | None:
    blob = data.attachments.get(CONFIG_ATTACHMENT)
    if blob is None:
        warnings.append(f"no {CONFIG_ATTACHMENT} attachment: drive settings taken from the run metadata")
        return None
    try:
        return parse_config_text(blob.decode("utf-8"), source=Path(CONFIG_ATTACHMENT))
    except (ValueError, ArithmeticError, RecursionError, TypeError, LookupError, DobHilError) as exc:
        warnings.append(f"{CONFIG_ATTACHMENT} attachment unusable ({_one_line(exc)})")
        return None


@dataclass(frozen=True)
class SampleSummary:
    """What :func:`interpret` needs of the samples when they are streamed, not held: their
    count, the median of the positive spacings of ``time_ns`` (None without any) and how many
    carry the DOB flag."""

    n: int
    median_spacing_ns: int | None
    dob_on: int


def median_spacing_ns(samples: StructArray) -> int | None:
    """Median of the positive spacings of the samples' ``time_ns`` (None without any)."""
    t = samples["time_ns"]
    median: int | None = None
    if len(t) >= 2:
        dt = np.diff(t.astype(np.int64))
        dt = dt[dt > 0]
        if len(dt):
            median = int(np.median(dt))
    return median


def _period_ns(
    path: Path,
    stats: SampleSummary | StructArray,
    run: dict[str, str],
    design: Design | None,
    warnings: list[str],
) -> int:
    period = _int_or_none(run.get("period_ns"))
    if period is not None:
        return period
    if design is not None:
        return design.period_ns
    median = stats.median_spacing_ns if isinstance(stats, SampleSummary) else median_spacing_ns(stats)
    if median is not None:
        warnings.append("no period in the run metadata or design: using the median sample spacing")
        return median
    raise DobHilError(f"{path}: the log holds neither a control period nor enough samples to infer one")


def _dob_enabled(stats: SampleSummary | StructArray, run: dict[str, str], warnings: list[str]) -> bool:
    text = run.get("dob_enabled")
    if text in ("true", "false"):
        return text == "true"
    if isinstance(stats, SampleSummary):
        n, on = stats.n, stats.dob_on
    else:
        n, on = len(stats), int(np.count_nonzero(stats["flags"] & FLAG_DOB_ON))
    if n:
        warnings.append("no dob_enabled in the run metadata: taken from the samples' DOB flag")
        return 2 * on >= n
    return False


def interpret(path: Path, data: LogData, stats: SampleSummary | None = None) -> LoadedLog:
    """Interpret an already read log (see the module docstring). ``stats``: the samples'
    summary when ``data`` holds no samples because they are streamed (:mod:`streamed`)."""
    samples: SampleSummary | StructArray = data.samples if stats is None else stats
    warnings = list(data.warnings)
    run = data.metadata.get("run", {})
    design = _design_of(data, warnings)
    config = _config_of(data, warnings)
    summary = data.metadata.get("summary")
    if summary is None:
        warnings.append("no summary record: the run did not close the log (crash or truncation)")
    else:
        dropped = _int_or_none(summary.get("dropped_records"))
        if dropped:
            warnings.append(
                f"{dropped} log records were dropped while the run wrote (the log writer fell behind)"
            )
            data.complete = False
    bitrate = _int_or_none(run.get("bitrate_bps"))
    if bitrate is None and config is not None:
        bitrate = config.drive.bitrate_bps
    return LoadedLog(
        path=path,
        data=data,
        design=design,
        config=config,
        period_ns=_period_ns(path, samples, run, design, warnings),
        dob_enabled=_dob_enabled(samples, run, warnings),
        mode=run.get("mode", "unknown"),
        bitrate_bps=bitrate,
        warnings=warnings,
    )


# What `dob-hil analyze` reads of each channel: everything its metrics and plots use, nothing
# more, so that an hour of samples (12 M at 3.33 kHz) fits in memory. Replay reads everything.
ANALYSIS_FIELDS: Final[dict[str, tuple[str, ...]]] = {
    TOPIC_SAMPLE: (
        "time_ns", "rx_time_ns", "tx_time_ns", "position", "x_ref", "x_hat", "x_bar", "u_dist",
        "u_cmd_a", "u_applied_a", "seq", "compute_ns", "feedback_seq", "flags",
    ),
    TOPIC_CAN: ("timestamp_ns", "arbitration_id", "direction", "dlc", "flags"),
    TOPIC_TRUTH: ("time_ns", "state", "disturbance_a", "period_index"),
}  # fmt: skip


def load_log(
    path: Path | str,
    *,
    topics: Iterable[str] | None = None,
    fields: Mapping[str, Iterable[str]] | None = None,
) -> LoadedLog:
    """Read and interpret one log. Raises LogReadError only for a file that is no log at all.

    ``fields`` (per topic) limits what is read, e.g. :data:`ANALYSIS_FIELDS`."""
    p = Path(path)
    return interpret(p, read_log(p, topics=topics, fields=fields))
