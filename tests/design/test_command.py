"""``dob-hil design``: JSON report on stdout, design file and plots on disk, one-line errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dob_hil.cli import main
from dob_hil.commands.design import write_design_outputs
from dob_hil.config import Config
from dob_hil.design import Design


def test_design_paper_step_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["design", "paper-step", "--json", "--out", str(tmp_path), "--no-plots"]) == 0
    out = capsys.readouterr().out
    report = json.loads(out)  # nothing but JSON on stdout
    np.testing.assert_allclose(report["Phi"], [[1.0, 2.9429e-4], [0.0, 9.6216e-1]], rtol=1e-4)
    np.testing.assert_allclose(report["Gam"], [[9.5445e-4], [6.3224]], rtol=1e-4)
    assert report["Lc"] == [[0.75], [0.5]] and report["Kc"] == [[107.42, 0.3]]
    assert report["Kdist"] == [[18.0, 3.75]] and report["Kdist_Lc"] == [[15.375]]
    radii = report["spectral_radii"]
    assert [round(v, 2) for v in radii["estimator"]] == [0.25, 0.96]
    assert [round(v, 2) for v in radii["feedback"]] == [0.89, 0.93]
    assert [round(v, 2) for v in radii["dob"]] == [0.28, 0.92]
    margins = report["loop_dob_on"]["margins_plant_input"][0]
    assert margins["gain_margin_dB"] > 6.0 and margins["phase_margin_deg"] > 30.0
    assert report["loop_dob_on"]["peak_sensitivity"]["value"] > 1.0
    # the config's 7 q values, extended by decades until recovery in the band, and the design's Kc
    rows = report["ltr"]["rows"]
    assert [r["q"] for r in rows[:7]] == [1.0, 10.0, 100.0, 1000.0, 1e4, 1e5, 1e6]
    assert rows[-2]["recovered_in_band"] and not any(r["recovered_in_band"] for r in rows[:-2])
    assert report["ltr"]["recovered_at_q"] == rows[-2]["q"] == 1e9
    assert rows[-1]["label"] == "design Kc"
    # issue 15's figures for the paper's gains
    dm = report["loop_dob_on"]["disk_margins_plant_input"][0]
    assert round(dm["gain_margin_dB"], 1) == 17.7 and round(dm["phase_margin_deg"], 1) == 75.2
    assert round(report["disturbance_estimate_filter"]["Q1"][0][0], 4) == 0.5055
    assert [p["kind"] for p in report["pole_flags"]] == ["negative real"]
    assert round(report["pole_flags"][0]["eigenvalue"][0], 2) == -0.93
    saved = Design.load(tmp_path / "design.json")
    assert saved.Kdist.tolist() == [[18.0, 3.75]]
    assert report["files"] == [str(tmp_path / "design.json")]


def test_design_text_report_and_plots(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["design", "paper-step", "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    for needle in (
        "Phi =",
        "Kdist Lc = [[15.375]]",
        "rho(Phi - Gam Kc)",
        "peak |S|",
        "loop transfer recovery",
    ):
        assert needle in text
    for name in (
        "design.json",
        "sensitivity.png",
        "disturbance.png",
        "dob_filter.png",
        "dob_locus.png",
        "ltr.png",
    ):
        data = (tmp_path / name).read_bytes()
        assert len(data) > 1000
        if name.endswith(".png"):
            assert data[:8] == b"\x89PNG\r\n\x1a\n"


def test_unstable_design_is_one_line_on_stderr(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "bad.toml"
    cfg.write_text(
        """
[plant]
A = [[0.0, 1.0], [0.0, -128.59]]
B = [0.0, 2.1484e4]
C = [[1.0, 0.0]]
period_us = 300.0
[design.estimator]
Lc = [0.75, 0.5]
[design.feedback]
Kc = [[107.42, 0.3]]
[design.dob]
Kdist = [[1800.0, 375.0]]
""",
        encoding="utf-8",
    )
    assert main(["design", str(cfg), "--out", str(tmp_path / "out"), "--no-plots"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("dob-hil design: error: dob: rho(Phi - Phi Lc C - Gam Kdist Lc C) = ")
    assert not (tmp_path / "out" / "design.json").exists()


def test_mimo_report_has_margins_per_channel(mimo_config: Config, tmp_path: Path) -> None:
    report = write_design_outputs(mimo_config, tmp_path, quiet=True, plots=False)
    for loop in ("loop_dob_on", "loop_dob_off"):
        assert len(report[loop]["margins_plant_input"]) == 2
        assert len(report[loop]["margins_plant_output"]) == 2
    assert len(report["spectral_radii"]["dob"]) == 4
    json.dumps(report, allow_nan=False)  # the report is plain JSON
    assert Design.load(tmp_path / "design.json").n_inputs == 2


def test_importing_the_design_package_stays_light() -> None:
    code = (
        "import sys, dob_hil.design; "
        "heavy = [m for m in ('control', 'matplotlib', 'scipy') if m in sys.modules]; "
        "print(','.join(heavy))"
    )
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    assert out.strip() == ""


def test_design_reports_the_worst_case_bus_load(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["design", "paper-step", "--json", "--no-plots", "--out", str(tmp_path)]) == 0
    load = json.loads(capsys.readouterr().out)["bus_load"]
    # 6-byte feedback (115 bit) + 3-byte command (85 bit) + a 10 Hz 2-byte heartbeat, 1 Mbit/s, 300 us
    assert load["frame_bits"] == {"FEEDBACK": 115, "COMMAND": 85, "HEARTBEAT": 75}
    assert load["worst_case_fraction"] == pytest.approx((115 + 85 + 75 * 10 * 300e-6) / 300, rel=1e-9)


def test_design_refuses_an_impossible_bus_load(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from dob_hil.scenarios import scenario_path

    text = scenario_path("paper-step").read_text().replace("bitrate_bps = 1000000", "bitrate_bps = 500000")
    cfg = tmp_path / "slow-bus.toml"
    cfg.write_text(text)
    assert main(["design", str(cfg), "--no-plots", "--out", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("dob-hil design: error: drive.bitrate_bps: worst-case bus load 13")
    assert len(err.splitlines()) == 1
