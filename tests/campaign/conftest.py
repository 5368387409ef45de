"""A tiny campaign (6 cases of 0.1 s: 3 draws, DOB on and off) shared by the campaign tests."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

TINY = """
[campaign]
name = "tiny"
base = "paper-step"
seed = 11
samples = 3
duration_s = 0.1
from_s = 0.02
keep_worst = 1
batch_size = 2

[[vary]]
key = "plant.A[1][1]"
relative = [-0.3, 0.3]

[[vary]]
key = "plant.B[1]"
relative = [-0.3, 0.3]

[[vary]]
key = "sim.disturbance[0].amplitude_A"
uniform = [0.0, 0.4]

[[vary]]
key = "sim.disturbance[0].frequency_hz"
uniform = [1.0, 20.0]

[[vary]]
key = "run.dob_enabled"
grid = [true, false]
"""


@pytest.fixture
def tiny_file(tmp_path: Path) -> Path:
    path = tmp_path / "tiny.toml"
    path.write_text(TINY, encoding="utf-8")
    return path


def write_tiny(folder: Path) -> Path:
    path = folder / "tiny.toml"
    path.write_text(TINY, encoding="utf-8")
    return path


@pytest.fixture(scope="session")
def tiny_writer() -> Callable[[Path], Path]:
    return write_tiny
