"""A lockstep run of a host-clocked scenario with triggers lost on the way to the drive, and the
check that every answered sample was taken at its own instant (the ODrive's RTR, CiA 402's SYNC)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dob_hil.config import load_config
from dob_hil.log import read_log
from dob_hil.loop.session import RunOptions, run_session
from dob_hil.scenarios import scenario_path
from firmware_sim.faulty_bus import FaultPlan, FaultyBus


def assert_samples_at_their_instants(scenario: str, trigger_id: int, lost: int, path: Path) -> None:
    """Lose ``lost`` triggers (frames of ``trigger_id`` from the host) from the 20th on, during the
    step's rise; each answered sample's position must equal the true position of its own period
    to the encoder's rounding (a sample one period late is many counts off there)."""
    config = load_config(scenario_path(scenario))
    plan = FaultPlan(tx_match=trigger_id, send_drop_at=20, send_drop_count=lost)
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
    assert max(errors) <= quantum, (int(np.argmax(errors)), max(errors) / quantum)
