"""The profile catalogue: the README's table is the registry's (it cannot go stale), and
``dob-hil profiles`` lists every profile with the bus load it gives for a config."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dob_hil.cli import main
from dob_hil.commands.profiles import README_BEGIN, README_END, markdown_table
from dob_hil.profiles import all_profiles

REPO_ROOT = Path(__file__).resolve().parents[1]


def test_readme_table_is_the_registrys() -> None:
    text = (REPO_ROOT / "README.md").read_text()
    assert README_BEGIN in text and README_END in text
    table = text.split(README_BEGIN, 1)[1].split(README_END, 1)[0].strip()
    assert table == markdown_table(), "regenerate the README table with `dob-hil profiles --markdown`"
    for profile in all_profiles():
        assert f"| `{profile.name}` |" in table


def test_profiles_json_for_a_config(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["profiles", "paper-step-odrive", "--json"]) == 0
    entries = {e["name"]: e for e in json.loads(capsys.readouterr().out)["profiles"]}
    assert set(entries) == {p.name for p in all_profiles()}
    odrive = entries["odrive"]
    assert odrive["min_period_ns"] == 1_000_000 and odrive["clocking"] == "host"
    # RTR (55 bit) + 2 x 8-byte frames (135 bit) per 1 ms + a heartbeat every 10 ms (13.5 bit),
    # worst-case stuffing
    assert odrive["config"]["bus_load_percent"] == pytest.approx(33.85, abs=0.01)
    assert odrive["config"]["period_ok"] is True
    assert entries["native"]["config"]["period_ok"] is True


def test_profiles_names_what_a_profile_cannot_do(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["profiles", "paper-step"]) == 0
    out = capsys.readouterr().out
    assert "300 us not served: 300 us is outside what the odrive profile serves (1000 to 1e+06 us)" in out
    assert "needs a [drive.odrive] table" in out
    assert main(["profiles", "no-such-config"]) == 2
