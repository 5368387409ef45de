"""dob-hil analyze through dob_hil.cli.main: JSON, the side-by-side table, the plots."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from analysis_support import rewrite_log

from dob_hil.cli import main
from dob_hil.commands.analyze import analyze_logs, default_plots_dir
from dob_hil.log import read_log

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
EXPECTED_PLOTS = {
    "output.png",
    "disturbance.png",
    "sensitivity.png",
    "tracking_error.png",
    "command.png",
}  # timing.png only for real-time logs (these are lockstep): tests/analysis/test_plots.py


def test_json_is_a_list_with_one_object_per_log_and_nothing_else(
    runs: dict[tuple[str, bool], Path], capsys: pytest.CaptureFixture[str]
) -> None:
    logs = [str(runs[("paper-sine", True)]), str(runs[("paper-sine", False)])]
    assert main(["analyze", *logs, "--json", "--no-plots", "--from", "0.05"]) == 0
    captured = capsys.readouterr()
    result = json.loads(captured.out)
    assert [r["file"] for r in result] == logs
    assert [r["dob_enabled"] for r in result] == [True, False]
    for r in result:
        assert r["window_start_s"] == pytest.approx(0.05, abs=3e-4)
        assert r["plots"] == []
        for key in (
            "samples",
            "duration_s",
            "tracking_error_rms",
            "tracking_error_max",
            "disturbance_estimate_error_rms",
            "estimation_error_rms",
            "saturated_fraction",
            "overruns",
            "dropped_samples",
            "latency_us",
            "period_jitter_us",
            "bus_load",
            "warnings",
        ):
            assert key in r
    assert captured.err == ""


def test_table_side_by_side_and_plots_overlaid(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    logs = [runs[("paper-step", True)], runs[("paper-step", False)]]
    plots = tmp_path / "plots"
    results = analyze_logs(logs, from_s=0.1, plots_dir=plots, as_json=False)
    out = capsys.readouterr().out
    header = out.splitlines()[0]
    assert "paper-step-dob (DOB on)" in header and "paper-step-nodob (DOB off)" in header
    row = next(line for line in out.splitlines() if line.startswith("tracking error rms"))
    assert len(row.split()) == 6  # name (3 words) + unit + one value per log
    assert "[rev]" in row
    assert {Path(p).name for p in results[0]["plots"]} == EXPECTED_PLOTS
    for name in EXPECTED_PLOTS:
        assert (plots / name).read_bytes()[:8] == PNG_MAGIC


def test_default_plots_dir_is_beside_the_first_log(tmp_path: Path) -> None:
    a, b = tmp_path / "a.mcap", tmp_path / "b.mcap"
    assert default_plots_dir([a]) == tmp_path / "a-plots"
    assert default_plots_dir([a, b]) == tmp_path / "a-vs-b-plots"


@pytest.mark.parametrize("value", ["-1", "nan"])
def test_bad_window_start(
    runs: dict[tuple[str, bool], Path], value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["analyze", str(runs[("paper-step", True)]), "--from", value, "--no-plots"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--from" in err[0]


def test_a_log_without_design_config_or_truth(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Metrics against the measured output, warnings naming what is missing, plots still drawn."""
    data = read_log(runs[("paper-step", True)])
    path = rewrite_log(data, tmp_path / "bare.mcap", truth=data.truth[:0], attachments={})
    results = analyze_logs([path], from_s=0.1, plots_dir=tmp_path / "p", as_json=True)
    captured = capsys.readouterr()
    (m,) = json.loads(captured.out)
    assert m == results[0]
    assert m["tracking_error_source"] == "measured" and m["truth_samples"] == 0
    assert m["disturbance_estimate_error_rms"] is None and m["estimation_error_rms"] is None
    # the measured output is the true one quantized to 1e-4 rev: the metric barely moves
    full = analyze_logs([runs[("paper-step", True)]], from_s=0.1, plots_dir=None, as_json=True, plots=False)[
        0
    ]
    capsys.readouterr()
    assert m["tracking_error_rms"] == pytest.approx(full["tracking_error_rms"], abs=1e-4)
    assert "no design.json attachment" in captured.err and "no config.toml attachment" in captured.err
    names = {Path(p).name for p in m["plots"]}
    assert names == EXPECTED_PLOTS - {"sensitivity.png"}
