"""The config: shipped scenarios parse, and every bad value is refused naming its field."""

from __future__ import annotations

import copy
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dob_hil.config import load_config, parse_config, parse_config_text
from dob_hil.errors import ConfigError
from dob_hil.scenarios import scenario_names, scenario_path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def paper() -> dict[str, Any]:
    return tomllib.loads(scenario_path("paper-step").read_text())


def test_shipped_scenarios_parse() -> None:
    assert {"paper-step", "paper-sine"} <= set(scenario_names())
    step = load_config(scenario_path("paper-step"))
    assert step.plant.period_ns == 300_000
    assert step.plant.B.shape == (2, 1)
    assert step.design.estimator.Lc is not None and step.design.estimator.Lc.shape == (2, 1)
    sine = load_config(scenario_path("paper-sine"))
    assert sine.reference.kind == "sine"
    assert [d.amplitude_A for d in sine.sim.disturbances] == [0.2, 0.1]
    assert [d.frequency_hz for d in sine.sim.disturbances] == [4.0, 12.0]


def mutate(path: str, value: Any) -> dict[str, Any]:
    data = paper()
    node = data
    keys = path.split(".")
    for key in keys[:-1]:
        node = node[key]
    if value is _DELETE:
        del node[keys[-1]]
    else:
        node[keys[-1]] = value
    return data


_DELETE = object()


@pytest.mark.parametrize(
    ("path", "value", "field", "problem"),
    [
        ("plant.A", _DELETE, "plant.A", "missing"),
        ("plant.A", [[0.0, 1.0, 2.0], [0.0, 1.0, 2.0]], "plant.A", "square"),
        ("plant.A", [[0.0, 1.0], [0.0]], "plant.A", "row 1 has 1"),
        ("plant.A", [[0.0, math.inf], [0.0, 1.0]], "plant.A", "finite"),
        ("plant.A", "abc", "plant.A", "matrix"),
        ("plant.B", [1.0, 2.0, 3.0], "plant.B", "rows"),
        ("plant.C", [[1.0, 0.0, 0.0]], "plant.C", "shape"),
        ("plant.period_us", -300.0, "plant.period_us", "> 0"),
        ("plant.period_us", 0.0, "plant.period_us", "> 0"),
        ("plant.period_us", math.nan, "plant.period_us", "finite"),
        ("plant.period_us", 300.0001, "plant.period_us", "whole number of ns"),
        ("plant.period_us", True, "plant.period_us", "number"),
        ("plant.input_delay_samples", -1, "plant.input_delay_samples", ">= 0"),
        ("plant.peroid_us", 300.0, "plant.peroid_us", "did you mean 'period_us'"),
        ("design.estimator.Lc", [0.75, 0.5, 0.1], "design.estimator.Lc", "shape"),
        ("design.feedback.Kc", [[1.0]], "design.feedback.Kc", "shape"),
        ("design.dob.Kdist", [[18.0, math.nan]], "design.dob.Kdist", "finite"),
        ("drive.current_limit_A", -0.7, "drive.current_limit_A", "> 0"),
        ("drive.current_limit_A", 100.0, "drive.current_limit_A", "int16"),
        ("drive.node_id", 200, "drive.node_id", "<= 127"),
        ("drive.encoder_bits", 40, "drive.encoder_bits", "<= 32"),
        ("drive.profile", "canopen-ish", "drive.profile", "one of"),
        ("sim.substeps", 0, "sim.substeps", ">= 1"),
        ("sim.loss_probability", 1.0, "sim.loss_probability", "< 1"),
        ("reference.kind", "ramp", "reference.kind", "one of"),
        ("run.duration_s", -1.0, "run.duration_s", "> 0"),
        ("run.missing_feedback_policy", "guess", "run.missing_feedback_policy", "one of"),
        ("plant", _DELETE, "plant", "missing"),
    ],
)
def test_bad_values_name_field_and_problem(path: str, value: Any, field: str, problem: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(mutate(path, value))
    assert info.value.field == field
    assert problem in info.value.problem


def test_disturbance_entries_are_checked() -> None:
    data = paper()
    data["sim"]["disturbance"][0]["kind"] = "chirp"
    with pytest.raises(ConfigError, match=r"sim\.disturbance\[0\]\.kind"):
        parse_config(data)


def test_invalid_toml_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not valid TOML"):
        parse_config_text("[plant\nA = 1")
    with pytest.raises(ConfigError, match="no such file"):
        load_config(tmp_path / "nope.toml")


def test_flat_lists_are_columns_where_columns_are_meant() -> None:
    cfg = parse_config(paper())
    np.testing.assert_array_equal(cfg.plant.B, [[0.0], [2.1484e4]])
    np.testing.assert_array_equal(cfg.design.estimator.Lc, [[0.75], [0.5]])


# --- property: any mutation either parses or raises ConfigError ------------------------------
_values = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**40), 2**40),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=5),
    st.lists(st.floats(-1e3, 1e3), max_size=4),
    st.lists(st.lists(st.floats(allow_nan=True), min_size=0, max_size=3), max_size=3),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2),
)


def _paths(d: dict[str, Any], prefix: str = "") -> list[str]:
    out = []
    for k, v in d.items():
        p = f"{prefix}{k}"
        out.append(p)
        if isinstance(v, dict):
            out.extend(_paths(v, p + "."))
    return out


PATHS = _paths(paper())


@settings(max_examples=1000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.sampled_from(PATHS), _values), min_size=1, max_size=3))
def test_generated_configs_parse_or_raise_config_error(edits: list[tuple[str, Any]]) -> None:
    data = copy.deepcopy(paper())
    for path, value in edits:
        node: Any = data
        keys = path.split(".")
        for key in keys[:-1]:
            if not isinstance(node, dict) or key not in node:
                break
            node = node[key]
        else:
            if isinstance(node, dict):
                if value is None:
                    node.pop(keys[-1], None)
                else:
                    node[keys[-1]] = value
    try:
        parse_config(data)
    except ConfigError as exc:
        assert exc.field and exc.problem


def test_scenario_variant_sets_node_and_patience(tmp_path: Path) -> None:
    from dob_hil.scenarios import scenario_variant

    cfg = load_config(scenario_variant("paper-step", tmp_path, node_id=42, patience_periods=200))
    assert cfg.drive.node_id == 42
    assert cfg.drive.watchdog_periods == cfg.drive.feedback_timeout_periods == 200
    plain = load_config(scenario_variant("paper-sine", tmp_path, node_id=7))
    assert plain.drive.node_id == 7 and plain.drive.watchdog_periods == 10


# --- schema: flat lists, shapes, suggestions, and the schema <-> parser <-> doc agreement ----------
def _delay_plant(extra: dict[str, Any] | None = None) -> dict[str, Any]:
    data = paper()
    data["plant"]["input_delay_samples"] = 1
    data["design"] = extra or {}
    return data


def test_flat_lists_are_columns_for_every_vector_field() -> None:
    cfg = parse_config(_delay_plant({"estimator": {"Gam1": [0, 1, 0], "D1": [1.0]}}))
    assert cfg.design.estimator.Gam1 is not None and cfg.design.estimator.Gam1.shape == (3, 1)
    cfg = parse_config(_delay_plant({"estimator": {"Lc": [0.5, 0.4, 0.1]}}))
    assert cfg.design.estimator.Lc is not None and cfg.design.estimator.Lc.shape == (3, 1)
    cfg = parse_config(_delay_plant({"feedback": {"Kc": [1.0, 0.1, 0.2]}, "dob": {"Kdist": [1.0, 0.1, 0.2]}}))
    assert cfg.design.feedback.Kc is not None and cfg.design.feedback.Kc.shape == (1, 3)


def test_a_shape_error_names_the_expected_shape_from_the_plant() -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(_delay_plant({"estimator": {"Lc": [0.75, 0.5]}}))
    assert info.value.field == "design.estimator.Lc"
    assert "expected shape 3x1" in info.value.problem
    assert "2 states + 1 delay samples x 1 inputs = 3" in info.value.problem


@pytest.mark.parametrize(
    ("path", "key", "suggestion"),
    [
        ("drive", "current_limt_A", "current_limit_A"),
        ("drive", "current_limit", "current_limit_A"),
        ("plant", "period", "period_us"),
        ("run", "duration", "duration_s"),
        ("sim", "nosie_counts_std", "noise_counts_std"),
    ],
)
def test_typos_get_a_suggestion_and_the_section_keys(path: str, key: str, suggestion: str) -> None:
    data = paper()
    data[path][key] = 1
    with pytest.raises(ConfigError) as info:
        parse_config(data)
    assert info.value.field == f"{path}.{key}"
    assert f"did you mean {suggestion!r}" in info.value.problem
    assert "valid keys here:" in info.value.problem
    assert suggestion in info.value.problem.split("valid keys here:")[1]


def test_a_wrong_choice_gets_a_suggestion() -> None:
    with pytest.raises(ConfigError, match=r"did you mean 'extrapolate'"):
        parse_config(mutate("run.missing_feedback_policy", "extrapolat"))


def test_every_schema_key_is_read_by_the_parser(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each section's parser asks for exactly the keys its schema declares: none undocumented,
    none documented but ignored."""
    from dob_hil import config as config_module
    from dob_hil.config_schema import SCHEMA, subsections

    asked: dict[str, list[str]] = {}
    original = config_module._Section.finish

    def spy(self: Any) -> None:
        asked.setdefault(self.path, []).extend(k for k in self.asked if k not in asked.get(self.path, []))
        original(self)

    monkeypatch.setattr(config_module._Section, "finish", spy)
    data = paper()
    data["sim"]["faults"] = {"fault_at_s": 0.5}
    data["reference"] = {"kind": "step"}
    parse_config(data)
    data["reference"] = {"outputs": [{"kind": "step"}]}  # [[reference.outputs]] instead of [reference]
    parse_config(data)
    for spec in SCHEMA:
        path = spec.path.replace("[]", "[0]")
        assert path in asked, path
        extra = set(asked[path]) - set(spec.keys) - set(subsections(spec.path.removesuffix("[]")))
        extra -= {"native"}  # the [drive.<profile>] table
        assert set(spec.keys) <= set(asked[path]), (path, set(spec.keys) - set(asked[path]))
        assert not extra, (path, extra)


def test_config_md_reference_is_generated_from_the_schema() -> None:
    """docs/CONFIG.md's reference block is exactly `dob-hil config --doc` (python3 tools/config_doc.py)."""
    from dob_hil.config_doc import BEGIN, END, render_reference

    doc = (Path(__file__).resolve().parents[1] / "docs" / "CONFIG.md").read_text(encoding="utf-8")
    assert BEGIN in doc and END in doc
    block = doc[doc.index(BEGIN) : doc.index(END) + len(END)] + "\n"
    assert block == render_reference(), "docs/CONFIG.md is stale: run python3 tools/config_doc.py"


def _toml_examples() -> list[tuple[str, str]]:
    import re

    doc = (Path(__file__).resolve().parents[1] / "docs" / "CONFIG.md").read_text(encoding="utf-8")
    out = []
    for match in re.finditer(r"\n#### ([^\n]+)\n.*?```toml\n(.*?)```", doc, re.S):
        out.append((match.group(1), match.group(2)))
    return out


@pytest.mark.parametrize(("title", "text"), _toml_examples(), ids=[t for t, _ in _toml_examples()])
def test_config_md_examples_parse_and_design(title: str, text: str, tmp_path: Path) -> None:
    from dob_hil.design import build_design

    (tmp_path / "reference.csv").write_text("time_s,position\n0.0,0.0\n0.5,1.0\n1.0,1.0\n")
    (tmp_path / "example.toml").write_text(text)
    cfg = load_config(tmp_path / "example.toml")
    design = build_design(cfg)
    n_aug = cfg.plant.n_states + cfg.plant.input_delay_samples * cfg.plant.n_inputs
    assert design.Phi.shape == (n_aug, n_aug)


def test_config_md_has_the_worked_examples() -> None:
    titles = " ".join(t.lower() for t, _ in _toml_examples())
    for topic in ("datasheet", "dare", "two-mass", "delay", "csv", "faults"):
        assert topic in titles, topic
