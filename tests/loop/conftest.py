from __future__ import annotations

from pathlib import Path

import pytest

from dob_hil.config import Config, load_config
from dob_hil.scenarios import scenario_path


@pytest.fixture(scope="session")
def paper_step() -> Config:
    return load_config(scenario_path("paper-step"))


@pytest.fixture(scope="session")
def paper_sine() -> Config:
    return load_config(scenario_path("paper-sine"))


@pytest.fixture
def log_path(tmp_path: Path) -> Path:
    return tmp_path / "run.mcap"
