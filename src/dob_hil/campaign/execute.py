"""One case, or a batch of them: a lockstep run through ``run_session`` (the code of
``dob-hil run``) and the metrics of ``dob-hil analyze`` (:mod:`dob_hil.analysis`) from its log.

The log goes to a scratch file that is deleted unless the case is kept (``keep_log``: a rerun,
or a failure with ``keep_failures``). A case that raises is a row with its error, never a crash
of the campaign. Rows hold plain values (JSON and Parquet ready); ``wall_s`` is the only column
that is not reproducible.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dob_hil.errors import DobHilError

if TYPE_CHECKING:
    from dob_hil.campaign.cases import Case
    from dob_hil.campaign.spec import CampaignSpec

# the metrics of dob_hil.analysis.metrics kept per case (reproducible, scalar)
METRIC_KEYS = (
    "tracking_error_rms",
    "tracking_error_max",
    "disturbance_rms",
    "disturbance_estimate_error_rms",
    "disturbance_estimate_gain",
    "saturated_fraction",
    "feedback_missing",
    "truth_samples",
)
STOP_SIGNALS = ("SIGINT", "SIGTERM")


def _metrics(path: Path, from_s: float) -> dict[str, Any]:
    from dob_hil.analysis.loaded import ANALYSIS_FIELDS, load_log
    from dob_hil.analysis.metrics import compute_metrics
    from dob_hil.analysis.signals import derive_signals

    log = load_log(path, fields=ANALYSIS_FIELDS)
    m = compute_metrics(log, from_s, derive_signals(log))
    return {k: m.get(k) for k in METRIC_KEYS}


def _num(value: Any) -> float:
    return float(value) if isinstance(value, int | float) and value is not None else math.nan


def run_case(spec: CampaignSpec, case: Case, keep_dir: Path | None, keep_log: bool = False) -> dict[str, Any]:
    """Run one case; its row. ``keep_dir``: where kept logs go (``<case_id>.mcap``)."""
    from dob_hil.campaign.cases import case_configs
    from dob_hil.loop.session import RunOptions, run_session

    row: dict[str, Any] = {"index": case.index, "case_id": case.case_id, "draw": case.draw, "seed": case.seed}
    row.update({f"param.{k}": v for k, v in case.params})
    fd, scratch = tempfile.mkstemp(prefix=f"dob-hil-{case.case_id}-", suffix=".mcap")
    os.close(fd)
    log_path = Path(scratch)
    t0 = time.perf_counter()
    error = ""
    exit_reason = "error"
    max_abs_current_A = math.nan
    dob: bool | None = case.dob_enabled
    try:
        design, truth, dob = case_configs(spec, case)
        options = RunOptions(dob_enabled=dob, duration_s=spec.duration_s, log_path=log_path, sim_config=truth)
        summary = run_session(design, options)
        exit_reason = summary.exit_reason
        max_abs_current_A = summary.max_abs_current_A
    except DobHilError as exc:  # a safety trip, a drive fault, a config the case made invalid
        exit_reason = f"{type(exc).__name__}: {exc}"
        error = exit_reason
    except Exception as exc:  # a crash: recorded, the campaign goes on
        exit_reason = "crash"
        error = f"{type(exc).__name__}: {exc}"
    metrics: dict[str, Any] = dict.fromkeys(METRIC_KEYS)
    try:
        if log_path.stat().st_size > 0:
            metrics = _metrics(log_path, spec.from_s)
    except Exception as exc:  # a log too short or damaged to analyse
        error = error or f"metrics: {type(exc).__name__}: {exc}"
    completed = exit_reason == "completed"
    err_max = _num(metrics["tracking_error_max"])
    row["dob_enabled"] = dob
    row["exit_reason"] = exit_reason
    row["error"] = error
    row["max_abs_current_A"] = max_abs_current_A
    row.update({k: _num(v) for k, v in metrics.items()})
    row["stable"] = completed and not error and err_max <= spec.stable_bound
    row["within_bound"] = bool(row["stable"] and err_max <= spec.tracking_bound)
    keep = keep_log or (spec.keep_failures and not completed and exit_reason not in STOP_SIGNALS)
    row["log"] = ""
    if keep and keep_dir is not None and log_path.exists():
        keep_dir.mkdir(parents=True, exist_ok=True)
        kept = keep_dir / f"{case.case_id}.mcap"
        shutil.move(str(log_path), kept)
        row["log"] = str(kept)
    log_path.unlink(missing_ok=True)
    row["wall_s"] = time.perf_counter() - t0
    return row


def run_batch(spec: CampaignSpec, cases: list[Case], keep_dir: str | None) -> list[dict[str, Any]]:
    """A batch of cases in one task (the unit of work of the pool and of Dask)."""
    rows = []
    for case in cases:
        row = run_case(spec, case, Path(keep_dir) if keep_dir else None)
        if row["exit_reason"] in STOP_SIGNALS:  # interrupted: not a result; resume redoes it
            raise KeyboardInterrupt
        rows.append(row)
    return rows
