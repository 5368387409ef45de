"""``replay --design`` streamed: the re-run chained block by block gives the rows and figures of the
whole log at once, in memory bounded by a block."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from analysis_support import run_log, scenario_text

from dob_hil.analysis import load_log
from dob_hil.analysis.downsample import DEFAULT_MAX_POINTS
from dob_hil.analysis.replay import _chain, logged_drive, logged_missing_policy, redesign, redesign_blocks
from dob_hil.cli import main
from dob_hil.commands.replay import load_other_design
from dob_hil.log.schemas import FLAG_FEEDBACK_MISSING

FIELDS = ("position", "x_hat", "x_bar", "u_fb", "u_dist", "u_cmd", "u_applied", "dac_counts", "saturated")


@pytest.fixture(scope="module")
def lossy_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """0.4 s of paper-step with 5 % of the feedback lost (substitutes, held commands)."""
    text = scenario_text("paper-step", **{"seed = 0\n": "seed = 3\nloss_probability = 0.05\n"})
    return run_log(tmp_path_factory.mktemp("lossy") / "lossy.mcap", text, dob=True, duration_s=0.4)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_chain_fed_in_blocks_gives_the_rows_of_one_pass(lossy_log: Path, seed: int) -> None:
    log = load_log(lossy_log)
    s = log.data.samples
    assert np.count_nonzero(s["flags"] & FLAG_FEEDBACK_MISSING) > 20
    assert log.design is not None
    notes: list[str] = []
    drive, missing = logged_drive(log, notes), logged_missing_policy(log, notes)
    whole = _chain(log, log.design, drive, missing).feed(s)
    chain = _chain(log, log.design, drive, missing)
    cuts = np.sort(np.random.default_rng(seed).choice(np.arange(1, len(s)), 12, replace=False))
    parts = [chain.feed(block) for block in np.split(s, cuts)]
    for name in FIELDS:
        joined = np.concatenate([getattr(p, name) for p in parts])
        np.testing.assert_array_equal(
            joined.view(np.uint8), getattr(whole, name).view(np.uint8), err_msg=name
        )
    assert chain.resyncs == whole.resyncs


def test_redesign_over_many_blocks_equals_the_whole_log(lossy_log: Path) -> None:
    log = load_log(lossy_log)
    other = load_other_design("paper-step-optimized", log.dob_enabled)
    expected = redesign(log, other)
    blocks = np.array_split(log.data.samples, 12)
    got = redesign_blocks(log, iter(blocks), other, total_samples=len(log.data.samples))
    a, b = expected.to_dict(), got.to_dict()
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], float) or (
            isinstance(a[key], list) and a[key] and isinstance(a[key][0], float)
        ):
            assert b[key] == pytest.approx(a[key], rel=1e-12), key
        else:
            assert a[key] == b[key], key
    assert got.rerun is None and got.series is not None
    n_inputs = got.series.sent_A.shape[1]
    # the plot keeps each drawn signal's envelope: every block's min and max of the difference
    assert len(got.series.t_s) <= 3 * n_inputs * (DEFAULT_MAX_POINTS + 2 * len(blocks))
    diff = got.series.other_A - got.series.sent_A
    assert expected.rerun is not None
    full = expected.rerun.u_applied - log.data.samples["u_applied_a"]
    assert diff.max() == full.max() and diff.min() == full.min()
    assert np.all(np.diff(got.series.t_s) > 0)


def test_the_command_streams_the_samples(lossy_log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = load_log(lossy_log)
    expected = redesign(log, load_other_design("paper-step-optimized", log.dob_enabled)).to_dict()
    assert main(["replay", str(lossy_log), "--design", "paper-step-optimized", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["samples"] == expected["samples"] == len(log.data.samples)
    assert out["u_applied_diff_max_A"] == expected["u_applied_diff_max_A"]
    assert out["u_applied_diff_rms_A"] == pytest.approx(expected["u_applied_diff_rms_A"], rel=1e-12)
    assert Path(out["plot"]).is_file()
