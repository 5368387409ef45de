"""paper-step-odrive end to end in lockstep against the simulated ODrive: the DOB at least halves
the tracking error (against the drive's true position), the current stays within the limit on the
wire, and the run ends with zero torque then IDLE."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from dob_hil.cli import main as dob_hil_main
from dob_hil.link.odrive.codec import CmdId
from dob_hil.log import read_log
from dob_hil.loop.session import RunOptions, run_session

from .odrive_support import NODE, odrive_config, odrive_text, tracking_rms

KT = 0.0827


def torques_on_the_wire(data) -> np.ndarray:  # type: ignore[no-untyped-def]
    f = data.frames
    tx = f[(f["direction"] == 1) & (f["arbitration_id"] == NODE << 5 | CmdId.SET_INPUT_TORQUE)]
    return np.array([struct.unpack("<f", bytes(row[:4]))[0] for row in tx["data"]])


def test_dob_halves_the_tracking_error(tmp_path: Path) -> None:
    config = odrive_config(tmp_path)
    rms = {}
    for dob in (True, False):
        log = tmp_path / f"dob-{dob}.mcap"
        summary = run_session(config, RunOptions(dob_enabled=dob, log_path=log))
        assert summary.exit_reason == "completed" and summary.samples == 1000
        data = read_log(log)
        rms[dob] = tracking_rms(data)
        torque = torques_on_the_wire(data)
        assert np.all(np.abs(torque) / KT <= 0.7)
        assert np.abs(data.samples["u_applied_a"]).max() <= 0.7
        tx = data.frames[data.frames["direction"] == 1]
        last_two = [(int(r["arbitration_id"]) & 0x1F, bytes(r["data"])) for r in tx[-2:]]
        assert last_two == [(CmdId.SET_INPUT_TORQUE, bytes(8)), (CmdId.SET_AXIS_STATE, bytes([1]) + bytes(7))]
    assert rms[True] <= 0.5 * rms[False], rms
    # the log replays bit for bit through the profile's own quantizer (float32 torque codes)
    assert dob_hil_main(["replay", str(tmp_path / "dob-True.mcap"), "--verify"]) == 0


def test_cli_runs_the_shipped_scenario(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status = dob_hil_main(["run", "--scenario", "paper-step-odrive", "--duration", "0.2", "--no-progress",
                           "--log", str(tmp_path / "cli.mcap")])  # fmt: skip
    assert status == 0, capsys.readouterr().err
    assert read_log(tmp_path / "cli.mcap").metadata["summary"]["exit_reason"] == "completed"


@pytest.mark.parametrize("command", ["design", "run"])
def test_a_period_below_one_ms_is_refused_naming_both_numbers(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    path = tmp_path / "fast.toml"
    path.write_text(odrive_text().replace("period_us = 1000.0", "period_us = 500.0"))
    assert dob_hil_main([command, str(path)]) == 2
    err = capsys.readouterr().err
    assert "plant.period_us: 500 us is outside what the odrive profile serves (1000 to 1e+06 us)" in err
    assert "Traceback" not in err
