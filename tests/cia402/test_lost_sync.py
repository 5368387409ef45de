"""A SYNC lost on the way to the simulated CiA 402 drive in lockstep: the drive's time runs on
without it (the runner's advance_period, counted by the SYNC-loss watchdog), and the samples
after the gap are taken at their own instants again (the ODrive counterpart:
tests/odrive/test_lost_trigger.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dob_hil.config import load_config
from dob_hil.log import read_log
from dob_hil.loop.session import RunOptions, run_session
from dob_hil.scenarios import scenario_path
from firmware_sim.faulty_bus import FaultPlan, FaultyBus

SYNC_ID = 0x80


@pytest.mark.parametrize("lost", [1, 3])
def test_samples_after_lost_triggers_are_taken_at_their_own_instants(tmp_path: Path, lost: int) -> None:
    config = load_config(scenario_path("paper-step-cia402"))
    path = tmp_path / "lost.mcap"
    plan = FaultPlan(tx_match=SYNC_ID, send_drop_at=20, send_drop_count=lost)  # during the step's rise
    run_session(
        config, RunOptions(duration_s=0.15, log_path=path, bus_wrapper=lambda bus: FaultyBus(bus, plan))
    )
    data = read_log(path)
    s, truth = data.samples, data.truth
    true_at = dict(zip(truth["period_index"].tolist(), truth["state"][:, 0].tolist(), strict=True))
    quantum = 1.0 / config.drive.encoder_counts_per_unit
    answered = s[s["rx_time_ns"] != 0]
    assert len(s) - lost - 1 <= len(answered) < len(s)  # the lost triggers went unanswered
    errors = [abs(float(row["position"][0]) - true_at[int(row["seq"])]) for row in answered]
    # the encoder's rounding at most, before and after the gap; a sample one period late would be
    # off by the distance the output moves in a period (many counts during the rise)
    assert max(errors) <= quantum, (np.argmax(errors), max(errors) / quantum)
