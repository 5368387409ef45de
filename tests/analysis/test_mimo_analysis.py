"""Analysis, replay and export of a 2x2 log, per output and per input.

The log is the coupled two-axis plant in closed loop with the project's controller, simulated and
written in :mod:`mimo_log_support`; every per-axis metric is checked against a numpy computation on
the simulated arrays themselves (not on what analysis read back)."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mimo_log_support import MIMO_TEXT, MimoRun, write_mimo_log
from test_plots import check_figure

from dob_hil import cli
from dob_hil.analysis import plots
from dob_hil.analysis.loaded import load_log
from dob_hil.analysis.metrics import compute_metrics
from dob_hil.analysis.replay import redesign, verify
from dob_hil.analysis.signals import derive_signals
from dob_hil.commands.analyze import analyze_logs
from dob_hil.config import parse_config_text
from dob_hil.design import build_design

FROM_S = 0.1
FIRST = 100  # the sample at 0.1 s (1 ms period)


@pytest.fixture(scope="module")
def mimo_runs(tmp_path_factory: pytest.TempPathFactory) -> dict[bool, MimoRun]:
    out = tmp_path_factory.mktemp("mimo")
    return {
        dob: write_mimo_log(out / f"mimo-{'dob' if dob else 'nodob'}.mcap", dob=dob) for dob in (True, False)
    }


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


@pytest.mark.parametrize("dob", [True, False])
def test_per_axis_metrics_match_a_numpy_computation_on_the_simulated_arrays(
    mimo_runs: dict[bool, MimoRun], dob: bool
) -> None:
    run = mimo_runs[dob]
    log = load_log(run.path)
    m = compute_metrics(log, FROM_S)
    w = slice(FIRST, None)
    e = run.y_ref[w] - run.y_true[w]
    assert m["tracking_error_source"] == "truth" and m["truth_samples"] == len(e)
    assert m["tracking_error_rms_per_output"] == pytest.approx([_rms(e[:, j]) for j in range(2)], rel=1e-12)
    assert m["tracking_error_max_per_output"] == pytest.approx(list(np.abs(e).max(axis=0)), rel=1e-12)
    # the combined keys stay: every output's samples together
    assert m["tracking_error_rms"] == pytest.approx(_rms(e), rel=1e-12)
    assert m["tracking_error_max"] == pytest.approx(float(np.abs(e).max()), rel=1e-12)
    dist, u_dist = run.w_A[w], run.u_dist[w]
    assert m["disturbance_rms_per_input"] == pytest.approx([_rms(dist[:, j]) for j in range(2)], rel=1e-12)
    assert m["disturbance_estimate_error_rms_per_input"] == pytest.approx(
        [_rms(dist[:, j] + u_dist[:, j]) for j in range(2)], rel=1e-12, abs=1e-15
    )
    gains = [float(np.dot(dist[:, j], -u_dist[:, j]) / np.dot(dist[:, j], dist[:, j])) for j in range(2)]
    assert m["disturbance_estimate_gain_per_input"] == pytest.approx(gains, rel=1e-9, abs=1e-15)
    applied = run.u_applied[w]
    assert m["current_rms_A_per_input"] == pytest.approx([_rms(applied[:, j]) for j in range(2)], rel=1e-12)
    assert m["current_max_A_per_input"] == pytest.approx(list(np.abs(applied).max(axis=0)), rel=1e-12)
    if dob:
        assert all(0.1 < g < 1.0 for g in m["disturbance_estimate_gain_per_input"])
    else:
        assert m["disturbance_estimate_gain_per_input"] == [0.0, 0.0]


def test_the_dob_lowers_the_tracking_error_of_each_output(mimo_runs: dict[bool, MimoRun]) -> None:
    on = compute_metrics(load_log(mimo_runs[True].path), FROM_S)
    off = compute_metrics(load_log(mimo_runs[False].path), FROM_S)
    for j in range(2):
        assert on["tracking_error_rms_per_output"][j] < 0.8 * off["tracking_error_rms_per_output"][j]


def test_without_truth_the_per_output_error_is_against_the_measurement(
    mimo_runs: dict[bool, MimoRun],
) -> None:
    log = load_log(mimo_runs[True].path)
    data = log.data
    log = dataclasses.replace(log, data=dataclasses.replace(data, truth=data.truth[:0]))
    m = compute_metrics(log, FROM_S)
    s = data.samples[FIRST:]
    e = np.asarray(s["x_ref"]) @ log.design.C.T - np.asarray(s["position"])  # type: ignore[union-attr]
    assert m["tracking_error_source"] == "measured"
    assert m["tracking_error_rms_per_output"] == pytest.approx([_rms(e[:, j]) for j in range(2)], rel=1e-12)
    assert m["disturbance_rms_per_input"] == [None, None]


def test_the_table_has_a_row_per_output_and_input(
    mimo_runs: dict[bool, MimoRun], capsys: pytest.CaptureFixture[str]
) -> None:
    results = analyze_logs([mimo_runs[True].path, mimo_runs[False].path], from_s=FROM_S, plots_dir=None,
                           as_json=False, plots=False)  # fmt: skip
    out = capsys.readouterr().out
    for j in (1, 2):
        row = next(
            line for line in out.splitlines() if line.startswith(f"tracking error rms output {j} [rev]")
        )
        values = [float(v) for v in row.split("]")[1].split()]
        expected = [r["tracking_error_rms_per_output"][j - 1] for r in results]
        assert values == pytest.approx(expected, rel=1e-3)
        assert f"w + u_dist rms input {j} [A]" in out
        assert f"current rms input {j} [A]" in out


def test_a_single_output_log_has_one_entry_per_list_and_no_axis_rows(
    runs: dict[tuple[str, bool], Path], capsys: pytest.CaptureFixture[str]
) -> None:
    [m] = analyze_logs(
        [runs[("paper-step", True)]], from_s=FROM_S, plots_dir=None, as_json=False, plots=False
    )
    out = capsys.readouterr().out
    assert "output 1" not in out and "input 1" not in out
    assert m["tracking_error_rms_per_output"] == [m["tracking_error_rms"]]
    assert m["tracking_error_max_per_output"] == [m["tracking_error_max"]]
    assert m["disturbance_estimate_error_rms_per_input"][0] == pytest.approx(
        m["disturbance_estimate_error_rms"]
    )
    assert m["disturbance_estimate_gain_per_input"][0] == pytest.approx(m["disturbance_estimate_gain"])


def test_json_per_axis_keys_through_the_cli(
    mimo_runs: dict[bool, MimoRun], capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli.main(["analyze", str(mimo_runs[True].path), "--json", "--no-plots"]) == 0
    [r] = json.loads(capsys.readouterr().out)
    for key in ("tracking_error_rms_per_output", "tracking_error_max_per_output"):
        assert len(r[key]) == 2
    for key in (
        "disturbance_rms_per_input",
        "disturbance_estimate_error_rms_per_input",
        "disturbance_estimate_gain_per_input",
        "current_rms_A_per_input",
        "current_max_A_per_input",
    ):
        assert len(r[key]) == 2


def _titles(fig: Any) -> list[str]:
    return [ax.get_title() for ax in fig.axes]


def test_plots_have_a_panel_per_output_and_input(
    mimo_runs: dict[bool, MimoRun], figures: dict[str, Any], tmp_path: Path
) -> None:
    inputs = []
    for dob in (True, False):
        log = load_log(mimo_runs[dob].path)
        inputs.append(plots.PlotInput(log, derive_signals(log)))
    written = plots.write_plots(inputs, tmp_path, from_s=FROM_S)
    assert {p.name for p in written} == {"output.png", "disturbance.png", "sensitivity.png",
                                         "tracking_error.png", "command.png"}  # fmt: skip
    for name, fig in figures.items():
        check_figure(name, fig)  # units on every axis, legends off the data
    for j, name in ((1, "p1"), (2, "p2")):
        label = f"output {j} ({name})"
        assert any(label in t and "plant output vs model output" in t for t in _titles(figures["output.png"]))
        assert any(label in t and "plant output minus model" in t for t in _titles(figures["output.png"]))
        assert sum(label in t for t in _titles(figures["tracking_error.png"])) == 2  # whole run, window
        assert any(ax.get_ylabel() == f"{label} [rev]" for ax in figures["output.png"].axes)
    for j, name in ((1, "i1"), (2, "i2")):
        label = f"input {j} ({name})"
        panel = next(ax for ax in figures["disturbance.png"].axes if label in ax.get_title())
        assert panel.get_ylabel() == f"{label} [A]"
        lines = [line.get_label() for line in panel.get_lines() if len(line.get_xdata())]
        assert any(re.search(r"gain 0\.\d\d x w", s) for s in lines), lines
        assert sum(label in t for t in _titles(figures["command.png"])) == 2  # one per run
    assert len(figures["command.png"].axes) == 4
    # each panel's data is its own axis: output 2's reference line is the second reference output
    out2 = next(ax for ax in figures["output.png"].axes if ax.get_ylabel() == "output 2 (p2) [rev]")
    ref = next(line for line in out2.get_lines() if line.get_label() == "reference")
    assert np.nanmax(np.abs(ref.get_ydata())) == pytest.approx(0.03, rel=1e-3)  # the 0.03 rev sine


def test_replay_verify_is_identical_per_axis(
    mimo_runs: dict[bool, MimoRun], capsys: pytest.CaptureFixture[str]
) -> None:
    for dob in (True, False):
        result = verify(load_log(mimo_runs[dob].path))
        assert result.identical, result.first_mismatches
        assert "x_ref" in result.fields  # rebuilt from [[reference.outputs]]
    assert cli.main(["replay", "--verify", str(mimo_runs[True].path)]) == 0
    assert "identical" in capsys.readouterr().out


def test_replay_verify_finds_a_changed_second_axis(mimo_runs: dict[bool, MimoRun], tmp_path: Path) -> None:
    from analysis_support import rewrite_log

    from dob_hil.log import read_log

    data = read_log(mimo_runs[True].path)
    samples = data.samples.copy()
    samples["u_applied_a"][300, 1] += 1.0 / 2048.0
    samples["x_ref"][400, 2] += 1e-9  # output 2's reference position
    path = rewrite_log(data, tmp_path / "edited.mcap", samples=samples, frames=False)
    result = verify(load_log(path))
    assert not result.identical
    assert result.mismatches_by_field["u_applied_a"] == 1
    assert result.mismatches_by_field["x_ref"] == 1
    assert result.first_mismatch_seq == 300


def test_replay_design_reports_each_input(
    mimo_runs: dict[bool, MimoRun], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    other_text = MIMO_TEXT.replace("gain = 0.5", "gain = 0.9").replace("mimo-2x2-synthetic", "mimo-other")
    other = build_design(parse_config_text(other_text))
    log = load_log(mimo_runs[True].path)
    result = redesign(log, other)
    sent = np.asarray(log.data.samples["u_applied_a"])
    assert result.rerun is not None
    diff = result.rerun.u_applied - sent
    assert result.sent_rms_A_per_input == pytest.approx([_rms(sent[:, j]) for j in range(2)], rel=1e-12)
    assert result.u_applied_diff_rms_A_per_input == pytest.approx(
        [_rms(diff[:, j]) for j in range(2)], rel=1e-12
    )
    assert all(d > 0 for d in result.u_applied_diff_rms_A_per_input)  # a stronger DOB on both axes
    path = tmp_path / "other.toml"
    path.write_text(other_text)
    assert cli.main(["replay", "--design", str(path), str(mimo_runs[True].path)]) == 0
    out = capsys.readouterr().out
    assert "input 1: sent rms" in out and "input 2: sent rms" in out


def test_export_has_a_column_per_axis(mimo_runs: dict[bool, MimoRun], tmp_path: Path) -> None:
    out = tmp_path / "samples.csv"
    assert (
        cli.main(["export", str(mimo_runs[True].path), "--format", "csv", "--samples", "--out", str(out)])
        == 0
    )
    with out.open(newline="") as f:
        rows = list(csv.DictReader(f))
    run = mimo_runs[True]
    assert len(rows) == len(run.u_applied)
    for j in range(2):
        applied = np.array([float(r[f"u_applied_a_{j}"]) for r in rows])
        np.testing.assert_array_equal(applied, run.u_applied[:, j])
        position = np.array([float(r[f"position_{j}"]) for r in rows])
        assert np.max(np.abs(position - run.y_true[:, j])) < 1e-3  # the encoder's quantisation
    assert math.isfinite(float(rows[-1]["x_ref_3"]))
