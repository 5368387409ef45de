"""Hostile ``[[reference.outputs]]`` through the CLI: one line on stderr naming the field, exit
status 2, no traceback, nothing opened (the pattern of test_bad_config.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from dob_hil import cli
from dob_hil.config import parse_config_text
from dob_hil.errors import ConfigError
from dob_hil.scenarios import scenario_path

PAPER = scenario_path("paper-step").read_text()
SINE = 'kind = "sine"\namplitude = 0.5\n'

# (case, text appended to the paper's config, what stderr must name)
BAD = [
    ("two tables for one output", f"[[reference.outputs]]\n{SINE}[[reference.outputs]]\n{SINE}",
     "reference.outputs: expected 1 tables"),
    ("wrong type", '[[reference.outputs]]\nkind = 5\n', "reference.outputs[0].kind"),
    ("unknown key with a suggestion", "[[reference.outputs]]\npositon = 0.3\n",
     "reference.outputs[0].positon"),
    ("wrong choice", '[[reference.outputs]]\nkind = "ramp"\n', "reference.outputs[0].kind"),
    ("above Nyquist", '[[reference.outputs]]\nkind = "sine"\nfrequency_hz = 5000.0\n',
     "reference.outputs[0].frequency_hz"),
    ("csv without a path", '[[reference.outputs]]\nkind = "csv"\n', "reference.outputs[0].path"),
    ("csv that does not exist", '[[reference.outputs]]\nkind = "csv"\npath = "nope.csv"\n',
     "reference.outputs[0].path"),
    ("position 1e308", "[[reference.outputs]]\nposition = 1e308\n", "reference.outputs[0].position"),
]  # fmt: skip


def _with_reference(text: str) -> str:
    """The paper's config with its [reference] table replaced by ``text``."""
    start = PAPER.index("[reference]\n")
    end = PAPER.index("\n[", start + 1) + 1
    return PAPER[:start] + text + PAPER[end:]


INLINE = [  # whole [reference] tables in inline form: what the array-of-tables syntax cannot say
    ("an empty list", "[reference]\noutputs = []\n", "reference.outputs: expected 1 tables"),
    ("not an array", "[reference]\noutputs = 3\n", "reference.outputs: expected an array of tables"),
    ("an entry not a table", "[reference]\noutputs = [1.0]\n", "reference.outputs[0]: expected a table"),
    ("a scalar key beside the tables",
     f"[reference]\nkind = \"sine\"\n[[reference.outputs]]\n{SINE}", "reference.kind"),
    ("a path beside the tables", f"[reference]\npath = \"a.csv\"\n[[reference.outputs]]\n{SINE}",
     "reference.path"),
]  # fmt: skip


CASES = [(case, PAPER + "\n" + extra, names) for case, extra, names in BAD] + [
    (case, _with_reference(text), names) for case, text, names in INLINE
]


@pytest.mark.parametrize(("case", "text", "names"), CASES, ids=[c[0] for c in CASES])
@pytest.mark.parametrize("command", ["run", "design"])
def test_bad_reference_outputs_is_one_line_with_status_2(
    command: str, case: str, text: str, names: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    if command == "run":
        argv = ["run", str(path), "--duration", "0.01", "--log", str(tmp_path / "x.mcap"), "--no-progress"]
    else:
        argv = ["design", str(path), "--out", str(tmp_path / "design"), "--no-plots"]
    rc = cli.main(argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"dob-hil {command}: error:")
    assert names in lines[0]
    assert "Traceback" not in err
    assert not (tmp_path / "x.mcap").exists()


def test_scalar_keys_beside_the_tables_name_both() -> None:
    text = _with_reference(f"[reference]\namplitude = 2.0\n[[reference.outputs]]\n{SINE}")
    with pytest.raises(ConfigError) as info:
        parse_config_text(text)
    assert info.value.field == "reference.amplitude"
    assert "reference.outputs" in info.value.problem


def test_default_scalar_keys_beside_the_tables_are_accepted() -> None:
    """The paper's [reference] spells out defaults (kind = "step", position = 1.0, start_s = 0.0):
    with [[reference.outputs]] they are no conflict."""
    cfg = parse_config_text(PAPER + f"\n[[reference.outputs]]\n{SINE}")
    assert len(cfg.reference.outputs) == 1
    assert cfg.reference.outputs[0].kind == "sine"
    assert cfg.reference.outputs[0].amplitude == 0.5


CSV_OUTPUTS = '[[reference.outputs]]\nkind = "csv"\npath = "{path}"\n'

BAD_CSV = [  # (case, CSV bytes): each must be named by the table that points at it
    ("not UTF-8", b"time_s,position\n0,0\n\xff\xfe,1\n"),
    ("empty", b""),
    ("times that do not increase", b"time_s,position\n0,0\n1,1\n0.5,2\n"),
    ("NaN position", b"time_s,position\n0,0\n1,nan\n"),
    # the central difference of two rows 1e-320 s apart is inf: refused, not commanded mid-run
    ("an infinite derived velocity", b"time_s,position\n0,0\n1e-320,1\n"),
    ("a derived velocity beyond the value bound", b"time_s,position\n0,0\n1e-300,1\n"),
]


@pytest.mark.parametrize(("case", "data"), BAD_CSV, ids=[c[0] for c in BAD_CSV])
def test_bad_csv_of_an_output_names_that_output(
    case: str, data: bytes, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "ref.csv").write_bytes(data)
    path = tmp_path / "bad.toml"
    path.write_text(_with_reference(CSV_OUTPUTS.format(path="ref.csv")))
    rc = cli.main(
        ["run", str(path), "--duration", "0.01", "--log", str(tmp_path / "x.mcap"), "--no-progress"]
    )
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("dob-hil run: error: reference.outputs[0].path"), lines[0]
    assert "Traceback" not in err
    assert not (tmp_path / "x.mcap").exists()


def test_bad_csv_of_the_single_reference_names_reference_path(tmp_path: Path) -> None:
    (tmp_path / "ref.csv").write_bytes(b"time_s,position\n0,0\n1e-320,1\n")
    text = _with_reference('[reference]\nkind = "csv"\npath = "ref.csv"\n')
    with pytest.raises(ConfigError) as info:
        parse_config_text(text, tmp_path / "bad.toml")
    assert info.value.field.startswith("reference.path"), info.value.field
    assert "velocity" in info.value.problem
