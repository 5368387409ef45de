"""Per-sample signals derived from a log, shared by the metrics and the plots (vectorised).

Every array has one row per logged sample, in file order:

- ``t_s``: sample instant relative to the first sample (or to ``t0_ns``, the first sample of the
  whole log when ``log`` holds a stretch of it), in seconds;
- ``y_ref``: reference output ``C x_ref`` (design C; without a design, the first p reference states);
- ``y_meas``: measured output (``position``); ``has_feedback``: the sample had real feedback
  (flag bit 2 clear and a receive time);
- ``truth_row``: the matched ground-truth record or -1 (:mod:`dob_hil.analysis.truth_match`);
- ``y_true``: true plant output ``C_cont x`` (NaN where no truth), ``x_true`` (plant states) and
  ``w_A`` (injected disturbance), NaN where no truth.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from dob_hil.analysis.loaded import LoadedLog
from dob_hil.analysis.truth_match import TruthMatch, match_truth
from dob_hil.log.schemas import FLAG_FEEDBACK_MISSING

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class Signals:
    t_s: FloatArray
    y_ref: FloatArray
    y_meas: FloatArray
    has_feedback: BoolArray
    truth: TruthMatch
    y_true: FloatArray
    x_true: FloatArray
    w_A: FloatArray

    @property
    def has_truth(self) -> BoolArray:
        return np.asarray(self.truth.index >= 0, dtype=np.bool_)


def _gather(values: npt.NDArray[Any], match: TruthMatch, rows_slice: slice | None) -> FloatArray:
    """values[rows] (2-D float64) with NaN rows where no truth matched; a view when possible."""
    if rows_slice is not None:
        return np.asarray(values[rows_slice], dtype=np.float64)
    rows = match.index
    if len(values) == 0:
        return np.full((len(rows), values.shape[1]), np.nan)
    out = np.asarray(values[np.maximum(rows, 0)], dtype=np.float64)
    out[rows < 0] = np.nan
    return out


def encoder_quantum(log: LoadedLog) -> float:
    """One encoder count in the output unit (config, else run metadata, else 0)."""
    if log.config is not None:
        return 1.0 / log.config.drive.encoder_counts_per_unit
    try:
        return 1.0 / float(log.run.get("encoder_counts_per_unit", "inf"))
    except (ValueError, ZeroDivisionError):
        return 0.0


def derive_signals(log: LoadedLog, t0_ns: int | None = None) -> Signals:
    s = log.data.samples
    truth = log.data.truth
    n = len(s)
    p = log.data.layout.n_outputs
    n_plant = log.data.layout.n_plant_states
    t_ns = s["time_ns"].view(np.int64)
    t_s = (t_ns - (t_ns[0] if t0_ns is None else t0_ns)) * 1e-9 if n else np.zeros(0)
    x_ref = s["x_ref"]
    y_meas = s["position"]
    has_fb = (s["flags"] & FLAG_FEEDBACK_MISSING) == 0
    design = log.design
    C = design.C if design is not None else np.eye(p, log.data.layout.n_states)
    C_cont = design.C_cont if design is not None else np.eye(p, n_plant)
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite rows: counted by the metrics
        y_ref = x_ref @ C.T
    states = truth["state"]
    match = match_truth(
        s["seq"].astype(np.int64),
        s["feedback_seq"].astype(np.int64),
        has_fb,
        y_meas,
        truth["period_index"].astype(np.int64),
        lambda rows: np.asarray(states[rows] @ C_cont.T, dtype=np.float64),
        encoder_quantum(log),
    )
    rows = match.as_slice()
    x_true = _gather(states, match, rows)
    return Signals(
        t_s=t_s,
        y_ref=np.asarray(y_ref, dtype=np.float64),
        y_meas=np.asarray(y_meas, dtype=np.float64),
        has_feedback=np.asarray(has_fb, dtype=np.bool_),
        truth=match,
        y_true=x_true @ C_cont.T,
        x_true=x_true,
        w_A=_gather(truth["disturbance_a"], match, rows),
    )
