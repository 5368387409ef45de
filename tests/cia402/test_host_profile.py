"""The cia402 profile descriptor: registry entry, bus load of its cyclic frames, [drive.cia402]
options and their errors, and the design warning for a delay the model leaves out."""

from __future__ import annotations

from pathlib import Path

import pytest

from dob_hil.commands.design import write_design_outputs
from dob_hil.config import parse_config_text
from dob_hil.errors import ConfigError
from dob_hil.link.busload import frame_bits
from dob_hil.link.cia402.options import DEFAULT_EDS, Cia402Options
from dob_hil.profiles import Clocking, get_profile
from dob_hil.scenarios import scenario_path

TEXT = scenario_path("paper-step-cia402").read_text()


def _config(old: str = "", new: str = "") -> object:
    assert old in TEXT
    return parse_config_text(TEXT.replace(old, new, 1))


def test_registered_host_clocked_with_one_period_of_delay() -> None:
    profile = get_profile("cia402")
    assert profile.clocking is Clocking.HOST and profile.input_delay_samples == 1
    profile.check_period(300_000)
    with pytest.raises(ConfigError, match=r"plant\.period_us"):
        profile.check_period(profile.min_period_ns - 1000)


def test_options_default_and_parsed() -> None:
    config = parse_config_text(TEXT)
    assert config.drive.options == Cia402Options()
    assert Cia402Options().eds_path == DEFAULT_EDS and DEFAULT_EDS.is_file()
    config = _config("map_velocity = false", "map_velocity = true")
    assert config.drive.options.map_velocity  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    ("old", "new", "field"),
    [
        ('# eds = "my-drive.eds"', 'eds = "no/such.eds"', "drive.cia402.eds"),
        ("heartbeat_ms = 100", "heartbeat_ms = -1", "drive.cia402.heartbeat_ms"),
        ("sdo_timeout_ms = 500", "sdo_timeout_ms = 0", "drive.cia402.sdo_timeout_ms"),
        ("sync_counter = false", "sync_counter = 1", "drive.cia402.sync_counter"),
        ("map_velocity = false", "map_velocity = false\nmap_velocty = true", "drive.cia402.map_velocty"),
    ],
)
def test_bad_options_name_the_field(old: str, new: str, field: str) -> None:
    with pytest.raises(ConfigError) as err:
        _config(old, new)
    assert err.value.field == field


def test_bus_load_counts_sync_rpdo_tpdo_and_heartbeat() -> None:
    profile = get_profile("cia402")
    load = profile.bus_load(parse_config_text(TEXT))  # type: ignore[arg-type]
    assert load.frame_bits == {"SYNC": frame_bits(0), "RPDO1": frame_bits(4), "TPDO1": frame_bits(6),
                               "HEARTBEAT": frame_bits(1)}  # fmt: skip
    assert load.frames_per_period["HEARTBEAT"] == pytest.approx(10.0 * 300e-6)
    expected_bits = frame_bits(0) + frame_bits(4) + frame_bits(6) + frame_bits(1) * 10.0 * 300e-6
    assert load.bits_per_period == pytest.approx(expected_bits)
    assert load.fraction == pytest.approx(expected_bits * 1e-6 / 300e-6)
    more = profile.bus_load(  # type: ignore[arg-type]
        _config("sync_counter = false\nmap_velocity = false", "sync_counter = true\nmap_velocity = true")
    )
    assert more.frame_bits["SYNC"] == frame_bits(1) and more.frame_bits["TPDO2"] == frame_bits(4)


def test_design_warns_when_the_profiles_delay_is_not_modelled(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    write_design_outputs(parse_config_text(TEXT), tmp_path / "ok", quiet=True, plots=False)
    assert "warning" not in capsys.readouterr().err
    text = (
        TEXT.replace("input_delay_samples = 1 ", "input_delay_samples = 0 ")
        .replace("Lc = [0.75, 0.5, 0.0]", "Lc = [0.75, 0.5]")
        .replace("Kc = [[107.42, 0.3202596100696233, 1.9992683821775672]]", "Kc = [[107.42, 0.3]]")
    )
    write_design_outputs(parse_config_text(text), tmp_path / "warn", quiet=True, plots=False)
    err = capsys.readouterr().err
    assert "the cia402 profile adds 1 sample(s) of input delay" in err
    assert "plant.input_delay_samples = 0" in err
