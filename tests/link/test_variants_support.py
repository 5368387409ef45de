"""A config for the lockstep simulated drive in the link tests (no disturbance: the loop is short)."""

from __future__ import annotations

from dob_hil.config import Config, parse_config
from dob_hil.scenarios import scenario_path


def lockstep_config() -> Config:
    import tomllib

    data = tomllib.loads(scenario_path("paper-step").read_text())
    data.setdefault("sim", {})["disturbance"] = []
    return parse_config(data)
