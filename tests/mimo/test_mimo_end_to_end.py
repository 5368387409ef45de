"""The shipped 2x2 scenario end to end, in lockstep and in real time: the DOB at least halves the tracking
error (against the simulated drive's ground truth) on both outputs, no current beyond the limit on any
axis, both drive nodes left disabled at zero current, every axis in the log."""

from __future__ import annotations

import dataclasses
import gc
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from log_checks import assert_log_times_monotonic
from mimo_support import mimo_config, patient, steady_tracking_rms, undisturbed_truth

import firmware_sim.axes
from dob_hil import cli
from dob_hil.analysis.bus_usage import clock_offset_ns
from dob_hil.config import Config
from dob_hil.design import build_design
from dob_hil.errors import ConfigError
from dob_hil.link.protocol import DriveState, FrameKind
from dob_hil.log import LogData, read_log
from dob_hil.log.schemas import FLAG_FEEDBACK_MISSING
from dob_hil.loop import session as session_module
from dob_hil.loop.session import RunOptions, RunSummary, run_session
from firmware_sim.axes import MultiAxisDrive

ERROR_FROM_S = 0.3  # after the step's transient


def _run(
    config: Config, log_path: Path, monkeypatch: pytest.MonkeyPatch, **options: Any
) -> tuple[RunSummary, LogData, MultiAxisDrive]:
    """run_session, keeping the simulated drive it builds (to check how it was left)."""
    made: list[MultiAxisDrive] = []
    factory = firmware_sim.axes.make_simulated_drive

    def keep(*args: Any, **kw: Any) -> Any:
        drive = factory(*args, **kw)
        assert isinstance(drive, MultiAxisDrive)
        made.append(drive)
        return drive

    monkeypatch.setattr(firmware_sim.axes, "make_simulated_drive", keep)
    summary = run_session(config, RunOptions(log_path=log_path, **options))
    return summary, read_log(log_path), made[0]


def _check_run(config: Config, summary: RunSummary, data: LogData, drive: MultiAxisDrive, log: Path) -> None:
    assert summary.exit_reason == "completed", summary.exit_reason
    limit = config.drive.current_limit_A
    applied = data.samples["u_applied_a"]
    assert applied.shape[1] == 2 and np.all(np.abs(applied) <= limit)
    assert np.all(np.abs(data.truth["applied_current_a"]) <= limit)
    assert summary.max_abs_current_A <= limit
    # both nodes left disabled at zero current
    assert drive.axis_states == (DriveState.DISABLED, DriveState.DISABLED)
    assert drive.applied_currents_A == (0.0, 0.0)
    # the log has every axis: per-input truth, both nodes' frames, one clock per channel
    assert data.truth["disturbance_a"].shape[1] == 2 and data.truth["state"].shape[1] == 4
    frames = data.frames
    for node in (1, 2):
        fb = np.count_nonzero(
            (frames["direction"] == 0) & (frames["arbitration_id"] == FrameKind.FEEDBACK + node)
        )
        cmd = np.count_nonzero(
            (frames["direction"] == 1) & (frames["arbitration_id"] == FrameKind.COMMAND + node)
        )
        assert (
            fb >= summary.samples - summary.missing_samples
            and cmd >= summary.samples - summary.skipped_samples
        )
    assert_log_times_monotonic(log)


def _errors(config: Config, data: LogData, keep: Any = None) -> np.ndarray:  # type: ignore[type-arg]
    design = build_design(config, dob_enabled=True)
    from_sample = round(ERROR_FROM_S / config.plant.period_s)
    return steady_tracking_rms(data, np.asarray(design.C), np.asarray(config.plant.C), from_sample, keep)


def test_lockstep_the_dob_halves_the_tracking_error_on_both_outputs(
    mimo: Config, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rms = {}
    for dob in (True, False):
        log = tmp_path / f"lockstep-{dob}.mcap"
        summary, data, drive = _run(mimo, log, monkeypatch, dob_enabled=dob)
        _check_run(mimo, summary, data, drive, log)
        assert summary.missing_samples == 0 and summary.samples == 1000
        rms[dob] = _errors(mimo, data)
    ratio = rms[False] / rms[True]
    assert np.all(ratio >= 2.0), ratio
    assert np.all(rms[True] > 0)


RT_ATTEMPTS = 3
SETTLE_S = 0.3  # the plant's course after a stall: a slow design's transient from far off
MIN_UNDISTURBED = 100  # truth records (0.1 s) to measure a run's error on
# a run that missed more of its feedback than this is not real-time control: measured on a
# 2-CPU VM, 1-3 % of the 1,000 samples missing idle, 13-22 % beside two CPU hogs, 30-76 % beside
# four or more (the embedded drive's threads share the loop's process)
MAX_MISSING_FRACTION = 1 / 3


def test_real_time_the_dob_halves_the_tracking_error_on_both_outputs(
    mimo: Config, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The embedded drive on its own threads (python-can ``virtual`` bus), drive-clocked; patient
    timeouts (1 s) so that a loaded machine's stalls end no run; every run is checked in full
    (completed, limits, both nodes left disabled at zero current, the log).

    The error is measured on the truth records no stall preceded within 0.3 s
    (:func:`undisturbed_truth`): a stall (the drive's timer thread or the loop starved for tens of
    ms on a busy 2-CPU machine) holds the currents open loop and throws the plant off its course,
    with or without the DOB. A pair of runs without enough undisturbed periods, or with a run that
    missed more than a third of its feedback (the loop answered too few samples to be closed-loop
    control), is run again (at most 3 times); if the machine never gives real time the CPU, the
    test says so and is skipped.
    A pair whose ratio falls short is run again too (a busy runner once made a DOB-on run miss
    many answers in a row short of a stall); the test fails if two pairs fall short and none
    halves the error on both outputs.
    """
    config = patient(mimo, 1000)
    starved: list[str] = []
    short: list[str] = []
    for attempt in range(RT_ATTEMPTS):
        rms = {}
        missing: dict[bool, int] = {}
        for dob in (True, False):
            log = tmp_path / f"realtime-{attempt}-{dob}.mcap"
            summary, data, drive = _run(config, log, monkeypatch, dob_enabled=dob, realtime=True,
                                        enable_timeout_s=30.0)  # fmt: skip
            _check_run(config, summary, data, drive, log)
            assert summary.mode == "realtime" and summary.samples == 1000
            missing[dob] = summary.missing_samples
            if summary.missing_samples > MAX_MISSING_FRACTION * summary.samples:
                starved.append(f"DOB {'on' if dob else 'off'}: {summary.missing_samples} samples missing")
                break
            keep = undisturbed_truth(data, settle_s=SETTLE_S)
            t_ns = data.truth["time_ns"].astype(np.int64)
            from_ns = int(data.samples["time_ns"][round(ERROR_FROM_S / config.plant.period_s)])
            measured = keep & (t_ns >= from_ns)
            if np.count_nonzero(measured) < MIN_UNDISTURBED:
                starved.append(f"DOB {'on' if dob else 'off'}: {np.count_nonzero(measured)} undisturbed")
                break
            rms[dob] = _errors(config, data, keep)
        if len(rms) == 2:
            ratio = rms[False] / rms[True]
            if np.all(ratio >= 2.0):
                return
            short.append(
                f"ratio {ratio.round(2).tolist()} "
                f"(missing: {missing[True]} with the DOB, {missing[False]} without)"
            )
    assert len(short) < 2, f"the DOB did not halve the error on both outputs: {short}"
    pytest.skip(
        f"the machine starved the real-time loop in {RT_ATTEMPTS} attempts ({'; '.join(starved)}; "
        f"at least {MIN_UNDISTURBED} undisturbed periods and at most {MAX_MISSING_FRACTION:.0%} of "
        f"the samples missing needed; short of 2x: {short})"
    )


def test_the_scenario_runs_from_the_command_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "cli.mcap"
    assert cli.main(["run", "--scenario", "mimo-2x2", "--duration", "0.2", "--log", str(log)]) == 0
    data = read_log(log)
    assert data.samples["position"].shape == (200, 2)
    assert data.metadata["summary"]["exit_reason"] == "completed"
    # every logged command is what the controller computes from the logged feedback, per axis
    assert cli.main(["replay", str(log), "--verify"]) == 0
    assert "identical" in capsys.readouterr().out
    # the bus load counts both nodes: a FEEDBACK and a COMMAND per node per period (analyze
    # pairs the samples with the first COMMAND of each period, not with every COMMAND)
    assert clock_offset_ns(data.samples, data.frames) == ("time_ns", 0)
    assert cli.main(["analyze", str(log), "--no-plots", "--json"]) == 0
    load = json.loads(capsys.readouterr().out)[0]["bus_load"]
    assert 4.0 <= load["frames_per_period"] <= 4.1


@pytest.mark.filterwarnings("ignore::dob_hil.design.robustness.DesignWarning")  # (not this test's subject)
def test_the_scenario_at_the_papers_period_overloads_the_bus_and_is_refused(tmp_path: Path) -> None:
    config = mimo_config({"period_us = 1000.0": "period_us = 300.0"})
    with pytest.raises(ConfigError, match=r"drive\.bitrate_bps: worst-case bus load 13\d%"):
        run_session(config, RunOptions(log_path=tmp_path / "never.mcap"))
    assert not (tmp_path / "never.mcap").exists()


def test_the_safety_envelope_watches_every_output_and_stops_both_nodes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Motor 2 commanded beyond [safety] max_abs_position (motor 1 stays within): the run stops
    naming output 1, both nodes left disabled at zero current."""
    from dob_hil.loop.envelope import SafetyTrip

    config = mimo_config(
        {"position = 1.0\n": "position = 0.2\n", "position = 0.5\n": "position = 1.0\n"},
        append="\n[safety]\nmax_abs_position = 0.8\n",
    )
    made: list[MultiAxisDrive] = []
    factory = firmware_sim.axes.make_simulated_drive

    def keep(*args: Any, **kw: Any) -> Any:
        made.append(factory(*args, **kw))  # type: ignore[arg-type]
        return made[-1]

    monkeypatch.setattr(firmware_sim.axes, "make_simulated_drive", keep)
    log = tmp_path / "trip.mcap"
    with pytest.raises(SafetyTrip, match=r"position 0\.8\d* \(output 1\) outside \[-0\.8, 0\.8\]"):
        run_session(config, RunOptions(log_path=log))
    assert made[0].axis_states == (DriveState.DISABLED, DriveState.DISABLED)
    assert made[0].applied_currents_A == (0.0, 0.0)
    data = read_log(log)
    assert np.all(np.abs(data.samples["position"][:, 0]) < 0.8)


def test_lost_feedback_of_one_node_makes_the_period_missing_never_mixed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """5 % of the FEEDBACK frames lost, each node's on its own: a period missing a node is a missing
    sample (the loop's policy bridges it), never one axis's counts with another period's."""
    config = mimo_config({"seed = 0\n": "seed = 0\nloss_probability = 0.05\n"})
    log = tmp_path / "lossy.mcap"
    summary, data, drive = _run(config, log, monkeypatch)
    _check_run(config, summary, data, drive, log)
    lost = drive.stats.feedback_lost
    assert lost > 0 and summary.missing_samples > 0
    # a period is missing when either node's frame of it was lost (both lost: one period)
    assert lost // 2 <= summary.missing_samples <= lost
    incomplete = [e for e in data.events if "incomplete" in e["message"]]
    assert 0 < len(incomplete) <= summary.missing_samples  # (a period with both lost opens none)
    s = data.samples
    answered = (s["flags"] & FLAG_FEEDBACK_MISSING) == 0
    # every answered sample's counts are both nodes' counts of that very period (ground truth)
    truth_at = {int(t): i for i, t in enumerate(data.truth["time_ns"])}
    idx = np.array([truth_at[int(t)] for t in s["time_ns"][answered]])
    y_true = data.truth["state"][idx][:, [0, 2]]
    np.testing.assert_allclose(s["position"][answered], y_true, atol=0.5 / 10000 + 1e-12)


WIDE_PLANT = """
[meta]
name = "wide"
[plant]
A = [[0.0, 1.0], [0.0, -20.0]]
B = [[0.0, 0.0], [100.0, 50.0]]
C = [[1.0, 0.0]]
period_us = 1000.0
[design.estimator]
Gam1 = [[0.0], [1.0]]
D1 = [[0.01]]
[design.feedback]
q = 1.0e4
R2 = [[1.0, 0.0], [0.0, 2.0]]
[design.dob]
method = "dc_loop_gain"
gain = 0.5
[drive]
current_limit_A = 3.0
encoder_counts_per_unit = 10000.0
"""


@pytest.mark.filterwarnings("ignore::dob_hil.design.robustness.DesignWarning")  # (not this test's subject)
def test_a_non_square_plant_is_one_line_and_leaves_no_bus_open(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    config = tmp_path / "wide.toml"
    config.write_text(WIDE_PLANT)
    assert cli.main(["run", str(config), "--duration", "0.05", "--log", str(tmp_path / "w.mcap")]) == 2
    gc.collect()  # python-can warns from a bus's __del__ when it was never shut down
    errors = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert len(errors) == 1 and "plant.C" in errors[0]
    assert not [r for r in caplog.records if "not properly shut down" in r.getMessage()]


@pytest.mark.parametrize(
    ("profile", "node_ids", "field"),
    [("cia402", None, "plant.B"), ("odrive", None, "plant.B"), ("native", (1, 20), "drive.node_ids")],
)
def test_a_plant_the_profile_cannot_drive_is_refused_before_any_bus_opens(
    mimo: Config, monkeypatch: pytest.MonkeyPatch, tmp_path: Path, profile: str, node_ids: Any, field: str
) -> None:
    """A real drive (an external bus) is never opened, let alone enabled, for a 2x2 plant on a
    one-axis profile or for axes without a valid node each."""

    def no_bus(*args: Any, **kw: Any) -> Any:
        raise AssertionError("a bus was opened")

    monkeypatch.setattr(session_module, "open_bus", no_bus)
    monkeypatch.setattr(session_module, "bus_pair", no_bus)
    drive = dataclasses.replace(mimo.drive, profile=profile, node_ids=node_ids)
    config = dataclasses.replace(mimo, drive=drive)
    options = RunOptions(log_path=tmp_path / "x.mcap", interface="virtual", channel="never-opened")
    with pytest.raises(ConfigError) as refused:
        run_session(config, options)
    assert refused.value.field == field
