"""Metrics of real runs: against independent per-sample computations and the design's facts."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from dob_hil.analysis import compute_metrics, load_log
from dob_hil.analysis.metrics import gap_accounting
from dob_hil.config import parse_config_text
from dob_hil.link.busload import worst_case_bus_load
from dob_hil.log.schemas import FLAG_SATURATED

FROM_S = 0.1


@pytest.mark.parametrize("scenario", ["paper-step", "paper-sine"])
def test_dob_reduces_the_tracking_error(runs: dict[tuple[str, bool], Path], scenario: str) -> None:
    on = compute_metrics(load_log(runs[(scenario, True)]), FROM_S)
    off = compute_metrics(load_log(runs[(scenario, False)]), FROM_S)
    assert on["tracking_error_source"] == off["tracking_error_source"] == "truth"
    assert on["tracking_error_rms"] < 0.75 * off["tracking_error_rms"]
    assert on["tracking_error_max"] < off["tracking_error_max"]
    # the estimate follows the disturbance at about half amplitude (the paper's Kdist: DOB loop DC
    # gain ~1.02, so u_dist ~ -0.5 w at low frequency); without the DOB there is no estimate
    assert 0.3 < on["disturbance_estimate_gain"] < 0.7
    assert off["disturbance_estimate_gain"] == 0.0
    assert off["disturbance_estimate_error_rms"] == pytest.approx(off["disturbance_rms"])
    assert on["disturbance_estimate_error_rms"] < off["disturbance_estimate_error_rms"]


def test_metrics_agree_with_a_per_sample_computation(runs: dict[tuple[str, bool], Path]) -> None:
    """Tracking, disturbance and estimation errors recomputed sample by sample with a dict lookup."""
    log = load_log(runs[("paper-sine", True)])
    m = compute_metrics(log, FROM_S)
    s, truth = log.data.samples, log.data.truth
    by_index = {int(t["period_index"]): t for t in truth}
    assert log.design is not None
    C, C_cont = log.design.C, log.design.C_cont
    e, d, x0 = [], [], []
    for row in s:
        if row["time_ns"] * 1e-9 < FROM_S - 1e-12:
            continue
        t = by_index[int(row["seq"])]
        e.append(float((C @ row["x_ref"])[0] - (C_cont @ t["state"])[0]))
        d.append(float(t["disturbance_a"][0] + row["u_dist"][0]))
        x0.append(float(t["state"][0] - row["x_hat"][0]))
    assert m["samples"] == len(e) == m["truth_samples"]
    assert m["tracking_error_rms"] == pytest.approx(math.sqrt(sum(v * v for v in e) / len(e)), rel=1e-12)
    assert m["tracking_error_max"] == pytest.approx(max(abs(v) for v in e), rel=1e-12)
    assert m["disturbance_estimate_error_rms"] == pytest.approx(math.sqrt(sum(v * v for v in d) / len(d)))
    assert m["estimation_error_rms"][0] == pytest.approx(math.sqrt(sum(v * v for v in x0) / len(x0)))
    flags = [int(r["flags"]) for r in s if r["time_ns"] * 1e-9 >= FROM_S - 1e-12]
    assert m["saturated_fraction"] == sum(1 for f in flags if f & FLAG_SATURATED) / len(flags)
    assert m["duration_s"] == pytest.approx(len(e) * log.period_ns * 1e-9)


def test_bus_load_matches_the_designed_traffic(runs: dict[tuple[str, bool], Path]) -> None:
    """One FEEDBACK + one COMMAND per period plus the 10 Hz heartbeat: the worst-case figure of
    dob_hil.link.busload, within a heartbeat's share of the window."""
    log = load_log(runs[("paper-step", True)])
    load = compute_metrics(log, FROM_S)["bus_load"]
    assert log.config is not None
    expected = worst_case_bus_load(log.config.drive, log.period_ns)
    assert load["bitrate_bps"] == log.config.drive.bitrate_bps
    assert load["worst_case"] == pytest.approx(expected.fraction, abs=0.002)
    assert load["nominal"] < load["worst_case"]
    assert load["frames_per_period"] == pytest.approx(2.0 + 10.0 * log.period_ns * 1e-9, abs=0.002)


def test_timing_and_counters(runs: dict[tuple[str, bool], Path]) -> None:
    log = load_log(runs[("paper-step", False)])
    m = compute_metrics(log, 0.0)
    assert m["samples"] == len(log.data.samples)
    assert m["overruns"] == m["feedback_missing"] == m["dropped_samples"] == m["skipped_samples"] == 0
    assert m["log_dropped_records"] == 0
    assert m["latency_us"]["n"] == m["samples"]
    assert 0.0 <= m["latency_us"]["p50"] <= m["latency_us"]["p99"] <= m["latency_us"]["max"]
    assert m["period_jitter_us"]["n"] == m["samples"] - 1
    assert m["mode"] == "lockstep" and any("lockstep" in n for n in m["notes"])
    assert m["complete"] is True and m["warnings"] == []


def test_window_past_the_end_gives_no_samples_and_a_warning(runs: dict[tuple[str, bool], Path]) -> None:
    m = compute_metrics(load_log(runs[("paper-step", True)]), 5.0)
    assert m["samples"] == 0
    assert m["tracking_error_rms"] is None and m["saturated_fraction"] is None and m["bus_load"] is None
    assert any("past the log's end" in w for w in m["warnings"])


def test_step_saturates_at_the_start_only(runs: dict[tuple[str, bool], Path]) -> None:
    """The 1-rev step asks for ~100 A: saturated at first, never after the transient."""
    log = load_log(runs[("paper-step", True)])
    assert compute_metrics(log, 0.0)["saturated_fraction"] > 0.0
    assert compute_metrics(log, FROM_S)["saturated_fraction"] == 0.0
    assert parse_config_text(log.data.attachments["config.toml"].decode()).drive.current_limit_A == 0.7
    assert np.all(np.abs(log.data.samples["u_applied_a"]) <= 0.7)


def test_gap_accounting_counts_only_absent_samples() -> None:
    seq = np.array([0, 1, 2, 6, 7, 20, 21], dtype=np.int64)  # 3..5 and 8..19 absent
    lost = {"kind": "feedback_lost", "data": {"first_sample": 3, "count": 3}}
    present = {"kind": "feedback_lost", "data": {"first_sample": 0, "count": 2}}  # samples logged
    partial = {"kind": "overrun_skip", "data": {"first_sample": 15, "count": 10}}
    assert gap_accounting(seq, []) == (0, 15)
    assert gap_accounting(seq, [lost, present]) == (3, 12)
    assert gap_accounting(seq, [lost, present, partial]) == (8, 7)
    assert gap_accounting(seq[:1], [lost]) == (0, 0)
