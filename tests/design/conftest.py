"""Shared helpers for the design tests: configs built from TOML text, and the paper's example."""

from __future__ import annotations

import textwrap

import pytest

from dob_hil.config import Config, load_config, parse_config_text
from dob_hil.design import Design, build_design
from dob_hil.scenarios import scenario_path

PAPER_PLANT = """
[plant]
A = [[0.0, 1.0], [0.0, -128.59]]
B = [0.0, 2.1484e4]
C = [[1.0, 0.0]]
period_us = 300.0
"""

# Two coupled axes, two currents in, two positions out (sampled at 1 kHz).
MIMO_PLANT = """
[plant]
A = [[0.0, 1.0, 0.0, 0.0], [-40.0, -20.0, 40.0, 5.0], [0.0, 0.0, 0.0, 1.0], [30.0, 5.0, -30.0, -25.0]]
B = [[0.0, 0.0], [100.0, 10.0], [0.0, 0.0], [-5.0, 80.0]]
C = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
period_us = 1000.0
state_names = ["p1", "v1", "p2", "v2"]
input_names = ["i1", "i2"]
output_names = ["p1", "p2"]
"""


def make_config(plant: str, design: str = "", run: str = "") -> Config:
    """A Config from TOML snippets (plant table, design tables, run table)."""
    text = textwrap.dedent(plant) + "\n" + textwrap.dedent(design) + "\n" + textwrap.dedent(run)
    return parse_config_text(text)


@pytest.fixture(scope="session")
def paper_config() -> Config:
    return load_config(scenario_path("paper-step"))


MIMO_DESIGN = """
[design.estimator]
Gam1 = [[0.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.0, 1.0]]
D1 = [[0.01, 0.0], [0.0, 0.02]]
[design.feedback]
q = 1.0e4
R2 = [[1.0, 0.0], [0.0, 2.0]]
[design.dob]
method = "dc_loop_gain"
gain = 0.5
"""

DELAY_DESIGN = """
[design.estimator]
D1 = [[1.0e-3]]
[design.feedback]
q = 1.0e5
[design.dob]
method = "dc_loop_gain"
gain = 0.5
"""


@pytest.fixture(scope="session")
def mimo_config() -> Config:
    return make_config(MIMO_PLANT, MIMO_DESIGN)


@pytest.fixture(scope="session")
def delay_config() -> Config:
    return make_config(PAPER_PLANT + "input_delay_samples = 2\n", DELAY_DESIGN)


@pytest.fixture(scope="session")
def designs(paper_config: Config, mimo_config: Config, delay_config: Config) -> dict[str, Design]:
    return {
        "paper": build_design(paper_config),
        "mimo": build_design(mimo_config),
        "delay": build_design(delay_config),
    }
