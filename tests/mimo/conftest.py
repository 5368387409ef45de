"""Fixtures of the multi-axis tests (helpers: mimo_support.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from dob_hil.config import Config, load_config
from dob_hil.scenarios import scenario_path


@pytest.fixture(scope="session")
def mimo() -> Config:
    return load_config(scenario_path("mimo-2x2"))


@pytest.fixture
def log_path(tmp_path: Path) -> Path:
    return tmp_path / "run.mcap"
