"""Whole lockstep runs on the embedded simulated drive, checked through the log."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dob_hil.config import Config
from dob_hil.design import Design
from dob_hil.link.protocol import FrameKind
from dob_hil.log import read_log
from dob_hil.log.schemas import FLAG_DOB_ON, FLAG_SATURATED
from dob_hil.loop.session import RunOptions, run_session

LIMIT_CODE = 1433  # floor(0.7 A / (1/2048 A))


def _tracking_error_rms(path: Path, from_s: float = 0.1) -> float:
    data = read_log(path)
    s, t = data.samples, data.truth
    true_pos = t["state"][: len(s), 0]  # truth period_index k is the state at sample k
    assert np.array_equal(t["period_index"][: len(s)], s["seq"])
    window = s["time_ns"] >= from_s * 1e9
    err = s["x_ref"][window, 0] - true_pos[window]
    return float(np.sqrt(np.mean(err**2)))


def test_paper_step_logs_every_sample_and_frame(paper_step: Config, log_path: Path) -> None:
    summary = run_session(paper_step, RunOptions(log_path=log_path))
    assert summary.exit_reason == "completed"
    assert summary.samples == summary.planned_samples == 3333
    data = read_log(log_path)
    assert data.complete and not data.warnings
    s = data.samples
    assert len(s) == 3333
    np.testing.assert_array_equal(s["seq"], np.arange(3333))
    np.testing.assert_array_equal(s["time_ns"], np.arange(3333) * 300_000)
    # safety: nothing beyond the limit was ever commanded, in counts or in amperes
    assert np.abs(s["dac_counts"]).max() <= LIMIT_CODE
    assert np.abs(s["u_applied_a"]).max() <= 0.7
    np.testing.assert_array_equal(s["u_applied_a"][:, 0], s["dac_counts"][:, 0] / 2048.0)
    sat = (s["flags"] & FLAG_SATURATED) != 0
    assert sat.any()  # the unit step saturates the 0.7 A limit at first
    assert np.all(np.abs(s["dac_counts"][sat, 0]) == LIMIT_CODE)
    assert np.all(s["flags"] & FLAG_DOB_ON)
    # every feedback received and every command sent is in the log, with its bytes
    f = data.frames
    rx_fb = f[(f["direction"] == 0) & (f["arbitration_id"] == FrameKind.FEEDBACK + 1)]
    tx_cmd = f[(f["direction"] == 1) & (f["arbitration_id"] == FrameKind.COMMAND + 1)]
    assert len(rx_fb) == 3334  # and the feedback after the last command, read to answer it with the stop
    assert len(tx_cmd) >= 3333
    codes = tx_cmd["data"][:3333, :2].copy().view("<i2")[:, 0]
    np.testing.assert_array_equal(codes, s["dac_counts"][:, 0])
    counts = rx_fb["data"][:3333, :4].copy().view("<i4")[:, 0]
    np.testing.assert_array_equal(counts, s["counts"][:, 0])
    # ground truth on its own channel, the design and config attached
    assert len(data.truth) >= 3333
    design = Design.from_json(data.attachments["design.json"].decode())
    assert design.Kdist.tolist() == [[18.0, 3.75]]
    assert b"paper-step" in data.attachments["config.toml"]
    assert json.loads(json.dumps(data.metadata["summary"]))  # a summary was written at close


def test_run_ends_with_zero_current_and_disable(paper_step: Config, log_path: Path) -> None:
    run_session(paper_step, RunOptions(log_path=log_path, duration_s=0.05))
    f = read_log(log_path).frames
    tx = f[f["direction"] == 1]
    last_cmd = tx[tx["arbitration_id"] == FrameKind.COMMAND + 1][-1]
    assert last_cmd["data"][0] == 0 and last_cmd["data"][1] == 0  # 0 DAC counts
    assert last_cmd["data"][2] & 0x80 == 0  # enable bit clear
    assert tx[-1]["arbitration_id"] == FrameKind.CONTROL + 1 and tx[-1]["data"][0] == 0  # disable


def test_dob_reduces_tracking_error(paper_step: Config, tmp_path: Path) -> None:
    on, off = tmp_path / "on.mcap", tmp_path / "off.mcap"
    run_session(paper_step, RunOptions(log_path=on, dob_enabled=True))
    run_session(paper_step, RunOptions(log_path=off, dob_enabled=False))
    e_on, e_off = _tracking_error_rms(on), _tracking_error_rms(off)
    assert e_on < 0.7 * e_off, (e_on, e_off)
    assert not np.any(read_log(off).samples["u_dist"])


def test_lockstep_is_deterministic(paper_sine: Config, tmp_path: Path) -> None:
    a, b = tmp_path / "a.mcap", tmp_path / "b.mcap"
    run_session(paper_sine, RunOptions(log_path=a, duration_s=0.2))
    run_session(paper_sine, RunOptions(log_path=b, duration_s=0.2))
    fields = ["counts", "x_hat", "x_bar", "u_cmd_a", "dac_counts"]
    sa, sb = read_log(a).samples, read_log(b).samples
    for name in fields:
        np.testing.assert_array_equal(sa[name], sb[name])


def test_dob_estimate_opposes_the_injected_disturbance(paper_sine: Config, log_path: Path) -> None:
    run_session(paper_sine, RunOptions(log_path=log_path))
    data = read_log(log_path)
    s, t = data.samples, data.truth
    window = s["time_ns"] >= 0.1e9
    u_dist = s["u_dist"][window, 0]
    w = t["disturbance_a"][: len(s)][window, 0]
    assert np.corrcoef(u_dist, w)[0, 1] < -0.9  # u_dist follows -w


def test_exception_in_the_loop_stops_safely(
    paper_step: Config, log_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from dob_hil.control import reference

    calls = {"n": 0}
    original = reference.StepReference.at

    def failing_at(self: reference.StepReference, k: int) -> tuple[float, ...]:
        calls["n"] += 1
        if calls["n"] > 100:
            raise RuntimeError("reference generator failed")
        return original(self, k)

    monkeypatch.setattr(reference.StepReference, "at", failing_at)
    with pytest.raises(RuntimeError, match="reference generator failed"):
        run_session(paper_step, RunOptions(log_path=log_path))
    data = read_log(log_path)
    assert data.complete
    assert len(data.samples) == 100
    assert "RuntimeError" in data.metadata["summary"]["exit_reason"]
    tx = data.frames[data.frames["direction"] == 1]
    last_cmd = tx[tx["arbitration_id"] == FrameKind.COMMAND + 1][-1]
    assert bytes(last_cmd["data"][:2]) == b"\x00\x00"  # zero current
    assert last_cmd["data"][2] & 0x80 == 0  # enable bit clear
    assert any(e["kind"] == "run_aborted" for e in data.events)
