"""Configs, logs and frames are parsed as data only: no pickle, eval, marshal or yaml.load in the
source tree, and exactly one exec: the controller step compiled from the design's dimensions."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from dob_hil.config import load_config
from dob_hil.control.step import Gains, compile_step
from dob_hil.design import build_design
from dob_hil.scenarios import scenario_path

ROOT = Path(__file__).resolve().parents[2]
TREES = [ROOT / "src" / "dob_hil", ROOT / "firmware_sim"]
FORBIDDEN = {
    "pickle": re.compile(r"\b(c?pickle|dill|shelve)\b"),
    "eval(": re.compile(r"(?<![\w.])eval\s*\("),
    "yaml.load(": re.compile(r"\byaml\.(unsafe_)?load\s*\("),
    "marshal": re.compile(r"\bmarshal\b"),
}
EXEC = re.compile(r"(?<![\w.])exec\s*\(")
ALLOWED_EXEC = ROOT / "src" / "dob_hil" / "control" / "step.py"


def _sources() -> list[Path]:
    files = sorted(p for tree in TREES for p in tree.rglob("*.py"))
    assert len(files) > 30  # the trees were found
    return files


def test_no_unsafe_deserialisation_in_the_source_tree() -> None:
    found = []
    for path in _sources():
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            for name, pattern in FORBIDDEN.items():
                if pattern.search(line):
                    found.append(f"{path.relative_to(ROOT)}:{n}: {name}: {line.strip()}")
    assert not found, "\n".join(found)


def test_exec_only_in_the_step_compiler() -> None:
    uses = [
        (path, n)
        for path in _sources()
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if EXEC.search(line) and not line.lstrip().startswith("#")
    ]
    assert [p for p, _ in uses] == [ALLOWED_EXEC], uses


def test_the_exec_source_holds_no_value_of_the_config() -> None:
    """The code given to exec comes from the matrix dimensions; every coefficient of the shipped
    scenarios' designs enters as a bound default, never as text."""
    for name in ("paper-step", "paper-sine"):
        design = build_design(load_config(scenario_path(name)))
        gains = Gains(design.Phi, design.Gam, design.C, design.Lc, design.Kc, design.Kdist)
        source = compile_step(gains).source
        assert not re.search(r"\d\.\d|\de[-+]?\d", source), source  # no float literal at all
        for matrix in (design.Phi, design.Gam, design.Lc, design.Kc, design.Kdist):
            for value in np.asarray(matrix).ravel():
                if value not in (0.0, 1.0):
                    assert repr(float(value)) not in source
