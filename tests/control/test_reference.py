from __future__ import annotations

import math
from pathlib import Path

import pytest

from dob_hil.config import ReferenceConfig
from dob_hil.control.reference import make_reference
from dob_hil.errors import ConfigError

PERIOD_S = 300e-6


def test_step_from_start_time() -> None:
    ref = make_reference(ReferenceConfig(kind="step", position=1.0, start_s=0.0), 2, PERIOD_S)
    assert ref.at(0) == (1.0, 0.0)
    late = make_reference(ReferenceConfig(kind="step", position=2.0, start_s=0.003), 3, PERIOD_S)
    assert late.at(9) == (0.0, 0.0, 0.0)
    assert late.at(10) == (2.0, 0.0, 0.0)


def test_sine_carries_its_derivative_as_velocity() -> None:
    ref = make_reference(ReferenceConfig(kind="sine", amplitude=1.0, frequency_hz=1.0), 2, PERIOD_S)
    for k in (0, 417, 1000, 2500):
        t = k * PERIOD_S
        pos, vel = ref.at(k)
        assert pos == pytest.approx(math.sin(2 * math.pi * t), abs=1e-12)
        assert vel == pytest.approx(2 * math.pi * math.cos(2 * math.pi * t), abs=1e-12)


def test_csv_interpolates_and_holds(tmp_path: Path) -> None:
    path = tmp_path / "ref.csv"
    path.write_text("time_s,position\n0.0,0.0\n0.003,3.0\n")
    ref = make_reference(ReferenceConfig(kind="csv", csv_path=path), 2, PERIOD_S)
    assert ref.at(5)[0] == pytest.approx(1.5)
    assert ref.at(5)[1] == pytest.approx(1000.0)
    assert ref.at(100) == (3.0, 0.0)


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("t,position\n0,0\n", "header"),
        ("time_s,position\n0,0\n0,1\n", "does not increase"),
        ("time_s,position\n0,abc\n", "not a number"),
        ("time_s,position\n0,nan\n", "non-finite"),
        ("time_s,position\n", "at least one data row"),
    ],
)
def test_bad_csv_names_the_problem(tmp_path: Path, text: str, problem: str) -> None:
    path = tmp_path / "ref.csv"
    path.write_text(text)
    with pytest.raises(ConfigError, match=problem):
        make_reference(ReferenceConfig(kind="csv", csv_path=path), 2, PERIOD_S)
