"""Campaign files and case generation: checked input, seeded draws, nominal design vs perturbed truth."""

from __future__ import annotations

from pathlib import Path

import pytest

from dob_hil.campaign.cases import case_configs, generate_cases
from dob_hil.campaign.spec import load_campaign
from dob_hil.errors import ConfigError

NOMINAL_A11 = -128.59
NOMINAL_B1 = 2.1484e4


def test_cases_cross_draws_with_grid_and_pair_dob(tiny_file: Path) -> None:
    spec = load_campaign(tiny_file)
    cases = generate_cases(spec)
    assert spec.n_cases == len(cases) == 6
    assert [c.case_id for c in cases] == [f"c{i:06d}" for i in range(6)]
    for on, off in zip(cases[0::2], cases[1::2], strict=True):
        assert on.seed == off.seed and on.draw == off.draw
        assert on.dob_enabled is True and off.dob_enabled is False
        assert on.params[:4] == off.params[:4]  # the same plant and disturbance: paired
    for c in cases:
        p = dict(c.params)
        assert 0.7 * NOMINAL_B1 <= p["plant.B[1]"] <= 1.3 * NOMINAL_B1
        assert 1.3 * NOMINAL_A11 <= p["plant.A[1][1]"] <= 0.7 * NOMINAL_A11
        assert 0.0 <= p["sim.disturbance[0].amplitude_A"] <= 0.4
        assert 1.0 <= p["sim.disturbance[0].frequency_hz"] <= 20.0
    assert len({c.seed for c in cases}) == 3
    assert generate_cases(load_campaign(tiny_file)) == cases  # reproducible from the file alone


def test_design_is_nominal_and_truth_perturbed(tiny_file: Path) -> None:
    spec = load_campaign(tiny_file)
    case = generate_cases(spec)[1]
    p = dict(case.params)
    design, truth, dob = case_configs(spec, case)
    assert dob is False
    assert design.plant.A[1][1] == NOMINAL_A11 and design.plant.B[1][0] == NOMINAL_B1
    assert truth.plant.A[1][1] == p["plant.A[1][1]"] and truth.plant.B[1][0] == p["plant.B[1]"]
    for cfg in (design, truth):  # the disturbance is the world's, seen by both
        assert cfg.sim.disturbances[0].amplitude_A == p["sim.disturbance[0].amplitude_A"]
        assert cfg.sim.seed == case.seed


@pytest.mark.parametrize(
    ("vary", "message"),
    [
        ('key = "plant.B[7]"\nuniform = [0.0, 1.0]', "no such value"),
        ('key = "plant.B[1]"\nuniform = [2.0, 1.0]', "lo <= hi"),
        ('key = "plant.B[1]"\nuniform = [0.0, 1.0]\ngrid = [1.0]', "exactly one distribution"),
        ('key = "plant..B"\nuniform = [0.0, 1.0]', "cannot read"),
        ('key = "sim.substeps"\ngrid = [0]', "substeps"),
    ],
)
def test_bad_campaign_is_one_clear_error(tmp_path: Path, vary: str, message: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(f'[campaign]\nbase = "paper-step"\nsamples = 2\n[[vary]]\n{vary}\n', encoding="utf-8")
    with pytest.raises(ConfigError, match=message.replace("[", r"\[")):
        load_campaign(path)


def test_unknown_campaign_key_and_missing_base(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text('[campaign]\nbase = "paper-step"\nsample = 2\n', encoding="utf-8")
    with pytest.raises(ConfigError, match=r"campaign\.sample"):
        load_campaign(path)
    path.write_text("[campaign]\nsamples = 2\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"campaign\.base"):
        load_campaign(path)


def test_shipped_study_is_the_papers_plant_in_1000_cases() -> None:
    root = Path(__file__).resolve().parents[2]
    spec = load_campaign(root / "campaigns" / "paper-robustness.toml")
    assert spec.n_cases == 1000 and spec.duration_s == 1.0
    cases = generate_cases(spec)
    design, truth, _ = case_configs(spec, cases[0])
    assert truth.plant.B[1][0] == dict(cases[0].params)["plant.B[1]"]
    assert design.plant.A[1][1] == NOMINAL_A11 and design.plant.B[1][0] == NOMINAL_B1
    amplitudes = [dict(c.params)["sim.disturbance[0].amplitude_A"] for c in cases]
    assert 0.0 <= min(amplitudes) < 0.01 and 0.39 < max(amplitudes) <= 0.4
    assert sum(c.dob_enabled is True for c in cases) == 500
