"""Fixtures: short real runs of both paper scenarios with and without the DOB (lockstep)."""

from __future__ import annotations

from pathlib import Path

import pytest
from analysis_support import run_log, scenario_text

RUN_S = 0.3  # 1000 samples: long enough for the disturbance (4 Hz) to act over a period


@pytest.fixture(scope="session")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[tuple[str, bool], Path]:
    """{(scenario, dob_enabled): log path} for paper-step and paper-sine, DOB on and off."""
    out = tmp_path_factory.mktemp("runs")
    logs = {}
    for scenario in ("paper-step", "paper-sine"):
        for dob in (True, False):
            path = out / f"{scenario}-{'dob' if dob else 'nodob'}.mcap"
            logs[(scenario, dob)] = run_log(path, scenario_text(scenario), dob=dob, duration_s=RUN_S)
    return logs
