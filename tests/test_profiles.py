"""The drive profile registry: discovery, lookup errors, period checks, and the native entry."""

from __future__ import annotations

import pytest

from dob_hil.config import parse_config_text
from dob_hil.errors import ConfigError
from dob_hil.profiles import Clocking, all_profiles, get_profile, profile_names
from dob_hil.scenarios import resolve_config_path


def test_native_is_registered_with_its_limits() -> None:
    assert "native" in profile_names()
    native = get_profile("native")
    assert native.clocking is Clocking.DRIVE
    assert native.input_delay_samples == 0
    assert native.min_period_ns <= 300_000 <= native.max_period_ns
    assert all(p.name in profile_names() for p in all_profiles())


def test_unknown_profile_names_the_field_and_the_choices() -> None:
    with pytest.raises(ConfigError) as err:
        get_profile("canopen-ish")
    assert err.value.field == "drive.profile"
    assert "native" in str(err.value)


def test_config_refuses_an_unknown_profile() -> None:
    text = resolve_config_path("paper-step").read_text().replace('profile = "native"', 'profile = "nope"')
    with pytest.raises(ConfigError, match=r"drive\.profile"):
        parse_config_text(text)


def test_period_outside_the_profile_range_is_refused_naming_both() -> None:
    native = get_profile("native")
    with pytest.raises(ConfigError, match=r"plant\.period_us") as err:
        native.check_period(native.min_period_ns - 1000)
    assert f"{native.min_period_ns / 1000:g}" in str(err.value)
    native.check_period(300_000)


def test_native_bus_load_matches_the_paper_figure() -> None:
    cfg = parse_config_text(resolve_config_path("paper-step").read_text())
    load = get_profile("native").bus_load(cfg)
    assert load.percent == pytest.approx(66.7, abs=0.1)
