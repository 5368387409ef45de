"""Bad configs through the CLI (one line on stderr naming the field, exit status 2, no traceback),
and generated configs through parse + design + bus-load check (only the documented errors)."""

from __future__ import annotations

import copy
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fault_support import config_text
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dob_hil import cli
from dob_hil.config import Config, parse_config
from dob_hil.design import Design, build_design
from dob_hil.errors import ConfigError, DesignError
from dob_hil.link.busload import check_bus_load
from dob_hil.scenarios import scenario_path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

PAPER = scenario_path("paper-step").read_text()


def _edit(old: str, new: str) -> str:
    assert old in PAPER, old
    return PAPER.replace(old, new)


# (case, config text, what stderr must name)
BAD_CONFIGS = [
    ("missing plant table", PAPER.replace("[plant]", "[plant_]"), "plant"),
    ("missing plant.A", _edit("A = [[0.0, 1.0], [0.0, -128.59]]\n", ""), "plant.A"),
    ("plant.A not square",
     _edit("A = [[0.0, 1.0], [0.0, -128.59]]", "A = [[0.0, 1.0, 2.0], [0.0, -128.59, 1.0]]"), "plant.A"),
    ("plant.C wrong width", _edit("C = [[1.0, 0.0]]", "C = [[1.0, 0.0, 0.0]]"), "plant.C"),
    ("estimator gain wrong shape", _edit("Lc = [0.75, 0.5]", "Lc = [0.75, 0.5, 0.1]"), "design.estimator.Lc"),
    ("non-finite current limit",
     _edit("current_limit_A = 0.7", "current_limit_A = inf"), "drive.current_limit_A"),
    ("NaN in a matrix", _edit("Kc = [[107.42, 0.3]]", "Kc = [[nan, 0.3]]"), "design.feedback.Kc"),
    ("negative period", _edit("period_us = 300.0", "period_us = -300.0"), "plant.period_us"),
    ("zero period", _edit("period_us = 300.0", "period_us = 0"), "plant.period_us"),
    ("string for an integer", _edit("node_id = 1", 'node_id = "one"'), "drive.node_id"),
    ("unknown key", _edit("watchdog_periods = 10", "watchdog_period = 10"), "drive.watchdog_period"),
    ("unstable feedback design", _edit("Kc = [[107.42, 0.3]]", "Kc = [[-107.42, 0.3]]"), "rho("),
    ("unstable estimator", _edit("Lc = [0.75, 0.5]", "Lc = [3.0, 0.5]"), "estimator"),
    ("impossible bus load", _edit("bitrate_bps = 1000000", "bitrate_bps = 125000"), "bus load"),
    ("negative fault time", config_text(faults={"fault_at_s": -1.0}), "sim.faults.fault_at_s"),
    ("unknown fault key", config_text(faults={"fault_at": 0.1}), "sim.faults.fault_at"),
    ("encoder jump without size",
     config_text(faults={"encoder_jump_at_s": 0.1}), "sim.faults.encoder_jump_counts"),
    ("not TOML", "[plant\nA = 1", "not valid TOML"),
]  # fmt: skip


@pytest.mark.parametrize(("case", "text", "names"), BAD_CONFIGS, ids=[c[0] for c in BAD_CONFIGS])
@pytest.mark.parametrize("command", ["run", "design"])
def test_bad_config_is_one_line_with_status_2(
    command: str, case: str, text: str, names: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    if command == "run":
        argv = ["run", str(path), "--duration", "0.01", "--log", str(tmp_path / "x.mcap"), "--no-progress"]
    else:
        argv = ["design", str(path), "--out", str(tmp_path / "design"), "--no-plots"]
    if command == "design" and names == "bus load":
        names = ""  # the design alone does not put frames on a bus: it may succeed
    rc = cli.main(argv)
    err = capsys.readouterr().err
    if not names:
        assert rc in (0, 2)
        return
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"dob-hil {command}: error:")
    assert names in lines[0]
    assert "Traceback" not in err
    assert not (tmp_path / "x.mcap").exists()  # refused before anything was opened


def test_missing_config_file_and_bad_duration(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["run", str(tmp_path / "nope.toml"), "--no-progress"]) == 2
    assert "nope.toml: no such config file" in capsys.readouterr().err
    good = tmp_path / "good.toml"
    good.write_text(PAPER)
    assert cli.main(["run", str(good), "--duration", "-1", "--log", str(tmp_path / "x.mcap")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("dob-hil run: error: --duration") and "Traceback" not in err


# --- property: generated configs through parse, design and the bus-load check ---------------------
def _paper() -> dict[str, Any]:
    return tomllib.loads(PAPER)


def _paths(d: dict[str, Any], prefix: str = "") -> list[str]:
    out = []
    for k, v in d.items():
        out.append(f"{prefix}{k}")
        if isinstance(v, dict):
            out.extend(_paths(v, f"{prefix}{k}."))
    return out


PATHS = [
    *_paths(_paper()),
    "sim.faults.fault_at_s",
    "sim.faults.encoder_jump_counts",
    "run.max_missing_periods",
]
_numbers = st.one_of(
    st.integers(-(2**40), 2**40),
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(-1e4, 1e4),
    st.sampled_from([0, 1, -1, 0.5, 1e-9, 1e9, 125_000, 8_000_000, 32767, 2.0**31]),
)
_values = st.one_of(
    st.none(),
    st.booleans(),
    _numbers,
    st.text(max_size=4),
    st.lists(_numbers, max_size=4),
    st.lists(
        st.lists(st.one_of(st.floats(-1e3, 1e3), st.just(float("nan"))), min_size=1, max_size=3),
        min_size=1,
        max_size=3,
    ),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2),
)
_designs: dict[bytes, Design | Exception] = {}


def _apply(data: dict[str, Any], path: str, value: Any) -> None:
    keys = path.split(".")
    node: Any = data
    for key in keys[:-1]:
        if not isinstance(node, dict):
            return
        node = node.setdefault(key, {})
    if isinstance(node, dict):
        if value is None:
            node.pop(keys[-1], None)
        else:
            node[keys[-1]] = value


def _largest(value: Any) -> float:
    """The largest finite magnitude of any number in a (nested) config value."""
    if isinstance(value, bool):
        return 0.0
    if isinstance(value, (int, float)):
        return abs(float(value)) if math.isfinite(float(value)) else 0.0
    if isinstance(value, dict):
        return max((_largest(v) for v in value.values()), default=0.0)
    if isinstance(value, list):
        return max((_largest(v) for v in value), default=0.0)
    return 0.0


def test_a_huge_period_is_refused_naming_the_field() -> None:
    data = _paper()
    data["plant"]["period_us"] = 1.3942742879823897e42
    with pytest.raises(ConfigError, match=r"plant\.period_us"):
        build_design(parse_config(data))


def _design_key(cfg: Config) -> bytes:
    p = cfg.plant
    return repr((p.A.tobytes(), p.B.tobytes(), p.C.tobytes(), p.period_ns, p.input_delay_samples,
                 cfg.design, cfg.run.dob_enabled)).encode()  # fmt: skip


@settings(max_examples=1000, deadline=None, suppress_health_check=[HealthCheck.too_slow], database=None)
@given(st.lists(st.tuples(st.sampled_from(PATHS), _values), min_size=1, max_size=3))
def test_generated_configs_design_or_raise_a_named_error(edits: list[tuple[str, Any]]) -> None:
    data = copy.deepcopy(_paper())
    for path, value in edits:
        _apply(data, path, value)
    try:
        cfg = parse_config(data)
    except ConfigError as exc:
        assert exc.field and exc.problem
        return
    # the same design inputs are designed once (build_design is deterministic; ~35 ms each)
    key = _design_key(cfg)
    if key not in _designs:
        try:
            _designs[key] = build_design(cfg)
        except (ConfigError, DesignError) as exc:
            _designs[key] = exc
    result = _designs[key]
    if isinstance(result, ConfigError):
        assert result.field and result.problem
    elif isinstance(result, DesignError):
        assert "rho(" in str(result) or "DARE" in str(result) or str(result)
    else:
        assert result.Kc.shape[1] == result.Phi.shape[0]
    try:
        load = check_bus_load(cfg.drive, cfg.plant.period_ns)
    except ConfigError as exc:
        assert exc.field in ("drive.bitrate_bps", "plant.period_us") or "bus" in exc.problem, exc
    else:
        assert 0.0 < load.fraction <= 1.0


@settings(
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
    database=None,
)
@given(edits=st.lists(st.tuples(st.sampled_from(PATHS), _values), min_size=1, max_size=2))
def test_generated_configs_through_the_cli(
    edits: list[tuple[str, Any]], tmp_path_factory: pytest.TempPathFactory
) -> None:
    """Any generated config: `dob-hil design` exits 0, or 2 with one line; never a traceback."""
    data = copy.deepcopy(_paper())
    for path, value in edits:
        _apply(data, path, value)
    tmp = tmp_path_factory.mktemp("cli")
    path = tmp / "gen.toml"
    path.write_text(_to_toml(data))
    import contextlib
    import io

    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = cli.main(["design", str(path), "--out", str(tmp / "d"), "--no-plots"])
    text = err.getvalue()
    assert "Traceback" not in text
    if rc == 2:
        assert len(text.strip().splitlines()) == 1 and text.startswith("dob-hil design: error:")
    else:
        assert rc == 0, text


def _to_toml(data: dict[str, Any], prefix: str = "") -> str:
    """A small TOML writer for the generated tables (values: numbers, strings, lists, booleans)."""
    lines: list[str] = []
    tables: list[tuple[str, dict[str, Any]]] = []
    arrays: list[tuple[str, list[dict[str, Any]]]] = []
    for k, v in data.items():
        key = _key(k)
        if isinstance(v, dict):
            tables.append((f"{prefix}{key}", v))
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            arrays.append((f"{prefix}{key}", v))
        else:
            lines.append(f"{key} = {_value(v)}")
    out = "\n".join(lines) + "\n"
    for name, table in tables:
        out += f"\n[{name}]\n" + _to_toml(table, f"{name}.")
    for name, items in arrays:
        for item in items:
            out += f"\n[[{name}]]\n" + _to_toml(item, f"{name}.")
    return out


def _key(k: str) -> str:
    return (
        k
        if k and all(c.isalnum() or c in "_-" for c in k)
        else '"' + k.replace("\\", "\\\\").replace('"', '\\"') + '"'
    )


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if v in (float("inf"), float("-inf")):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return '"' + "".join(c if c.isprintable() and c not in '"\\' else f"\\u{ord(c):04x}" for c in v) + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(type(v))


# design-focused: finite perturbations of the plant, the gains and the period, so that most parse
# and reach the design; a design returned must be stable by an independent eigenvalue computation
_scale = st.floats(0.2, 5.0)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow], database=None)
@given(
    a22=st.floats(-2000.0, 200.0),
    b2=st.floats(1e2, 1e6),
    lc=st.tuples(_scale, _scale),
    kc=st.tuples(st.floats(-3.0, 3.0), _scale),
    kd=st.tuples(st.floats(-3.0, 3.0), _scale),
    period_us=st.sampled_from([50.0, 100.0, 300.0, 1000.0, 5000.0]),
    bitrate=st.sampled_from([125_000, 250_000, 500_000, 1_000_000]),
    delay=st.integers(0, 2),
)
def test_perturbed_designs_are_stable_or_refused(
    a22: float, b2: float, lc: tuple[float, float], kc: tuple[float, float], kd: tuple[float, float],
    period_us: float, bitrate: int, delay: int,
) -> None:  # fmt: skip
    data = _paper()
    data["plant"].update(
        A=[[0.0, 1.0], [0.0, a22]], B=[0.0, b2], period_us=period_us, input_delay_samples=delay
    )
    data["drive"]["bitrate_bps"] = bitrate
    if delay:  # explicit gains have the augmented size: use the DAREs instead
        data["design"] = {}
    else:
        data["design"]["estimator"]["Lc"] = [0.75 * lc[0], 0.5 * lc[1]]
        data["design"]["feedback"]["Kc"] = [[107.42 * kc[0], 0.3 * kc[1]]]
        data["design"]["dob"]["Kdist"] = [[18.0 * kd[0], 3.75 * kd[1]]]
    cfg = parse_config(data)
    try:
        design = build_design(cfg)
    except (DesignError, ConfigError) as exc:
        assert "rho(" in str(exc) or "DARE" in str(exc) or isinstance(exc, ConfigError), exc
    else:

        def rho(M: Any) -> float:
            return float(np.max(np.abs(np.linalg.eigvals(M))))

        Phi, Gam, C, Lc, Kc, Kd = design.Phi, design.Gam, design.C, design.Lc, design.Kc, design.Kdist
        assert rho(Phi - Gam @ Kc) < 1.0
        assert rho(Phi - Phi @ Lc @ C) < 1.0
        assert rho(Phi - Phi @ Lc @ C - Gam @ Kd @ Lc @ C) < 1.0  # the DOB is on in paper-step
    try:
        load = check_bus_load(cfg.drive, cfg.plant.period_ns)
    except ConfigError as exc:
        assert "bus load" in str(exc) or exc.field in ("drive.bitrate_bps", "plant.period_us"), exc
        assert period_us <= 300.0 or bitrate < 1_000_000
    else:
        assert 0.0 < load.fraction <= 1.0
