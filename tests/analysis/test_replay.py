"""replay --verify and --design on real runs, on runs with lost feedback, and on tampered logs."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from analysis_support import rewrite_log, run_log, scenario_text

from dob_hil.analysis import load_log
from dob_hil.analysis.metrics import compute_metrics
from dob_hil.analysis.replay import redesign, verify
from dob_hil.cli import main
from dob_hil.config import load_config
from dob_hil.design import build_design
from dob_hil.errors import DesignError
from dob_hil.log import read_log
from dob_hil.log.schemas import FLAG_FEEDBACK_MISSING


@pytest.mark.parametrize("scenario", ["paper-step", "paper-sine"])
@pytest.mark.parametrize("dob", [True, False])
def test_verify_reproduces_every_command_bit_for_bit(
    runs: dict[tuple[str, bool], Path], scenario: str, dob: bool, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["replay", str(runs[(scenario, dob)]), "--verify", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["identical"] is True and out["mismatched_samples"] == 0
    assert out["dob_enabled"] is dob
    assert {"u_cmd_a", "dac_counts", "u_applied_a", "x_hat", "x_bar", "x_ref"} <= set(out["fields"])


@pytest.mark.parametrize("policy", ["hold", "extrapolate", "zero"])
def test_verify_with_lost_feedback(tmp_path: Path, policy: str) -> None:
    """Feedback frames lost (5%): the substitutes of each missing-feedback policy are reproduced."""
    text = scenario_text(
        "paper-step",
        **{
            "seed = 0\n": "seed = 3\nloss_probability = 0.05\n",
            "dob_enabled = true\n": f"dob_enabled = true\nmissing_feedback_policy = '{policy}'\n"
            "max_missing_periods = 1\n",
        },
    )
    log = load_log(run_log(tmp_path / f"{policy}.mcap", text, dob=True, duration_s=0.2))
    missing = np.count_nonzero(log.data.samples["flags"] & FLAG_FEEDBACK_MISSING)
    assert missing > 10
    result = verify(log)
    assert result.identical, result.first_mismatches
    assert compute_metrics(log, 0.0)["feedback_missing"] == missing


def _tampered(runs: dict[tuple[str, bool], Path], tmp_path: Path, field: str, k: int) -> Path:
    data = read_log(runs[("paper-sine", True)])
    samples = data.samples.copy()
    samples[field][k, 0] = np.nextafter(samples[field][k, 0], np.inf)  # one ulp
    return rewrite_log(data, tmp_path / f"tampered-{field}.mcap", samples=samples)


@pytest.mark.parametrize("field", ["u_cmd_a", "x_bar"])
def test_verify_reports_a_one_ulp_difference_with_its_sample(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, field: str, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _tampered(runs, tmp_path, field, 500)
    assert main(["replay", str(path), "--verify"]) == 1
    out = capsys.readouterr().out
    assert "DIFFERENT" in out and "1 sample(s) differ, first at seq 500" in out
    result = verify(load_log(path))
    assert result.mismatches_by_field[field] == 1
    assert sum(result.mismatches_by_field.values()) == 1
    assert result.first_mismatches[0].seq == 500 and result.first_mismatches[0].field == field


def test_samples_lost_from_the_log(runs: dict[tuple[str, bool], Path], tmp_path: Path) -> None:
    """Ten sample records missing: dropped (unexplained), the re-run restarts after the gap; with a
    runner event explaining the gap they count as skipped instead."""
    data = read_log(runs[("paper-step", True)])
    keep = np.ones(len(data.samples), dtype=bool)
    keep[400:410] = False
    path = rewrite_log(data, tmp_path / "gap.mcap", samples=data.samples[keep])
    log = load_log(path)
    m = compute_metrics(log, 0.0)
    assert (m["dropped_samples"], m["skipped_samples"]) == (10, 0)
    result = verify(log)
    assert result.identical and result.resyncs == [410]
    event = {
        "time_ns": 0,
        "level": "warning",
        "kind": "feedback_lost",
        "message": "10 lost",
        "data": {"first_sample": 400, "count": 10},
    }
    explained = rewrite_log(
        data, tmp_path / "skip.mcap", samples=data.samples[keep], events=[*data.events, event]
    )
    m = compute_metrics(load_log(explained), 0.0)
    assert (m["dropped_samples"], m["skipped_samples"]) == (0, 10)


def test_design_same_gains_commands_the_same(
    runs: dict[tuple[str, bool], Path], capsys: pytest.CaptureFixture[str]
) -> None:
    """paper-sine has the same plant and gains as paper-step: not a single bit differs."""
    assert main(["replay", str(runs[("paper-step", True)]), "--design", "paper-sine", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["u_applied_diff_max_A"] == 0.0 and out["u_cmd_diff_max_A"] == 0.0
    assert Path(out["plot"]).is_file()


def test_design_with_another_kdist(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    other = tmp_path / "half-kdist.toml"
    edits = {'name = "paper-step"': 'name = "half-kdist"', "Kdist = [[18.0, 3.75]]": "Kdist = [[9.0, 1.875]]"}
    other.write_text(scenario_text("paper-step", **edits))
    assert main(["replay", str(runs[("paper-step", True)]), "--design", str(other)]) == 0
    out = capsys.readouterr().out
    assert "half-kdist" in out
    log = load_log(runs[("paper-step", True)])
    result = redesign(log, build_design(load_config(other), dob_enabled=True))
    assert result.u_applied_diff_rms_A > 1e-3
    # until the two estimators part ways (sample 1: same x_bar, same innovation) the other
    # design's disturbance compensation is exactly half the logged one
    assert result.rerun is not None
    u_dist = log.data.samples["u_dist"][:, 0]
    assert result.rerun.u_dist[1, 0] == pytest.approx(0.5 * u_dist[1], rel=1e-12)
    assert u_dist[1] != 0.0


def test_design_that_cannot_run_on_the_log_is_refused(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    other = tmp_path / "delayed.toml"
    edits = {'output_unit = "rev"\n': 'output_unit = "rev"\ninput_delay_samples = 1\n'}
    other.write_text(scenario_text("paper-step", **edits))
    assert main(["replay", str(runs[("paper-step", True)]), "--design", str(other)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("dob-hil replay: error:")
    log = load_log(runs[("paper-step", True)])
    assert log.design is not None
    with pytest.raises(DesignError, match="period 600000 ns differs from the log's 300000 ns"):
        redesign(log, dataclasses.replace(log.design, period_ns=600_000))


def test_verify_without_design_attachment(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = read_log(runs[("paper-step", False)])
    config_only = {"config.toml": data.attachments["config.toml"]}
    path = rewrite_log(data, tmp_path / "nodesign.mcap", attachments=config_only)
    assert main(["replay", str(path), "--verify"]) == 2
    err = capsys.readouterr().err
    assert "no usable design.json" in err and "Traceback" not in err
