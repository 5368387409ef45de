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


# --- hostile configs (issue 10): one line naming the field, exit 2, nothing opened ---------------
_BIG = "1" + "0" * 400
HOSTILE_CONFIGS = [
    ("integer beyond float range", _edit("current_limit_A = 0.7", f"current_limit_A = {_BIG}"),
     "drive.current_limit_A"),
    ("integer beyond float range in a matrix", _edit("Kc = [[107.42, 0.3]]", f"Kc = [[{_BIG}, 0.3]]"),
     "design.feedback.Kc"),
    ("integer beyond float range as the period", _edit("period_us = 300.0", f"period_us = {_BIG}"),
     "plant.period_us"),
    ("integer of 5000 digits", _edit("node_id = 1\n", "node_id = 1" + "0" * 5000 + "\n"), "line "),
    ("arrays nested 5000 deep", PAPER + "\n[meta2]\nx = " + "[" * 5000 + "]" * 5000 + "\n", "nested"),
    ("NUL in a string", _edit('output_unit = "rev"', 'output_unit = "r\\u0000ev"'), "plant.output_unit"),
    ("escape sequence in a name", _edit('state_names = ["position", "velocity"]',
                                        'state_names = ["\\u001b[2J", "velocity"]'), "plant.state_names[0]"),
    ("Kdist of -1e308", _edit("Kdist = [[18.0, 3.75]]", "Kdist = [[-1e308, 3.75]]"), "design.dob.Kdist"),
    ("encoder noise 1e308", _edit("noise_counts_std = 0.0", "noise_counts_std = 1e308"),
     "sim.noise_counts_std"),
    ("initial state 1e305", _edit("seed = 0\n", "seed = 0\ninitial_state = [1e305, 0]\n"),
     "sim.initial_state"),
    ("encoder counts 1e308", _edit("encoder_counts_per_unit = 10000.0", "encoder_counts_per_unit = 1e308"),
     "drive.encoder_counts_per_unit"),
    ("encoder counts 1e-300", _edit("encoder_counts_per_unit = 10000.0", "encoder_counts_per_unit = 1e-300"),
     "drive.encoder_counts_per_unit"),
    ("disturbance amplitude 1e308", _edit("amplitude_A = 0.2", "amplitude_A = 1e308"),
     "sim.disturbance[0].amplitude_A"),
    ("disturbance frequency 1e308", _edit("frequency_hz = 4.0 ", "frequency_hz = 1e308 "),
     "sim.disturbance[0].frequency_hz"),
    ("disturbance start 1e308", _edit('kind = "sine"\n', 'kind = "sine"\nstart_s = 1e308\n'),
     "sim.disturbance[0].start_s"),
    ("reference start 1e308", _edit("start_s = 0.0\n", "start_s = 1e308\n"), "reference.start_s"),
    ("sine reference above Nyquist",
     _edit('kind = "step"\nposition = 1.0\nstart_s = 0.0\n', 'kind = "sine"\nfrequency_hz = 1e308\n'),
     "reference.frequency_hz"),
    ("run duration 1e308", _edit("duration_s = 1.0", "duration_s = 1e308"), "run.duration_s"),
    ("CPU -1", _edit("dob_enabled = true", "dob_enabled = true\ncpu_affinity = [-1, 100000]"),
     "run.cpu_affinity"),
    ("name with ../", _edit('name = "paper-step"', 'name = "../../escaped"'), "meta.name"),
    ("name with a slash", _edit('name = "paper-step"', 'name = "a/b"'), "meta.name"),
    ("300-state plant", _edit("A = [[0.0, 1.0], [0.0, -128.59]]", f"A = {[[0.0] * 300] * 300}"), "plant.A"),
    ("100 delay samples", _edit("period_us = 300.0", "period_us = 300.0\ninput_delay_samples = 100"),
     "plant.input_delay_samples"),
    ("typo with a suggestion", _edit("current_limit_A = 0.7", "current_limt_A = 0.7"), "current_limit_A"),
]  # fmt: skip


@pytest.mark.parametrize(("case", "text", "names"), HOSTILE_CONFIGS, ids=[c[0] for c in HOSTILE_CONFIGS])
@pytest.mark.parametrize("command", ["run", "design"])
def test_hostile_config_is_one_line_with_status_2(
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
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"dob-hil {command}: error:")
    assert names in lines[0]
    assert len(lines[0]) < 600  # never a dump of the config
    assert not (tmp_path / "x.mcap").exists()
    assert not (tmp_path.parent / "escaped").exists()


def test_a_typo_gets_a_suggestion_and_the_valid_keys(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "typo.toml"
    path.write_text(_edit("current_limit_A = 0.7", "current_limt_A = 0.7"))
    assert cli.main(["design", str(path), "--no-plots", "--out", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert "drive.current_limt_A: unknown key (did you mean 'current_limit_A'?)" in err
    assert "valid keys here: profile, node_id, bitrate_bps, current_limit_A" in err


@pytest.mark.parametrize(
    ("argv_tail", "names"),
    [
        (["--duration=inf"], "--duration"),
        (["--duration=nan"], "--duration"),
        (["--duration", "1e308"], "--duration"),
        (["--cpu", "-1"], "--cpu"),
        (["--cpu", "100000"], "--cpu"),
        (["--log", "README.md/x.mcap"], "--log"),
    ],
)
def test_bad_run_options_are_one_line(
    argv_tail: list[str], names: str, tmp_path: Path, capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:  # fmt: skip
    (tmp_path / "README.md").write_text("a file, not a folder\n")
    monkeypatch.chdir(tmp_path)
    path = tmp_path / "good.toml"
    path.write_text(PAPER)
    argv = ["run", str(path), "--no-progress"]
    if "--log" not in argv_tail:
        argv += ["--log", str(tmp_path / "x.mcap")]
    rc = cli.main(argv + argv_tail)
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.startswith(f"dob-hil run: error: {names}") and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "x.mcap").exists()


def test_a_config_cpu_this_machine_lacks_is_refused_by_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "cpu.toml"
    path.write_text(_edit("dob_enabled = true", "dob_enabled = true\ncpu_affinity = [4095]"))
    rc = cli.main(["run", str(path), "--no-progress", "--log", str(tmp_path / "x.mcap")])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("dob-hil run: error: run.cpu_affinity: CPU 4095 is not one"), err
    assert not (tmp_path / "x.mcap").exists()
    parse_config(tomllib.loads(path.read_text()))  # a log's copy still parses on any machine


def test_an_unwritable_log_folder_is_refused_before_the_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import os

    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        if os.access(ro, os.W_OK):
            pytest.skip("running as root: a read-only folder is still writable")
        path = tmp_path / "good.toml"
        path.write_text(PAPER)
        rc = cli.main(["run", str(path), "--no-progress", "--log", str(ro / "sub" / "x.mcap")])
        err = capsys.readouterr().err
        assert rc == 2 and err.startswith("dob-hil run: error: --log: cannot create folder"), err
        path.write_text(_edit("dob_enabled = true", f'dob_enabled = true\nlog_dir = "{ro}"'))
        rc = cli.main(["run", str(path), "--no-progress"])
        err = capsys.readouterr().err
        assert rc == 2 and err.startswith("dob-hil run: error: run.log_dir: cannot write into folder"), err
    finally:
        ro.chmod(0o755)


def test_a_read_only_file_system_is_refused_before_the_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """EROFS from mkdir, and a folder the OS says cannot be written (as on a read-only mount)."""
    import errno
    import os

    from dob_hil.commands import paths

    path = tmp_path / "good.toml"
    path.write_text(PAPER)

    def erofs(self: Path, *args: object, **kwargs: object) -> None:
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(self))

    with monkeypatch.context() as m:
        m.setattr(Path, "mkdir", erofs)
        rc = cli.main(["run", str(path), "--no-progress", "--log", str(tmp_path / "new" / "x.mcap")])
    err = capsys.readouterr().err
    assert rc == 2 and "--log: cannot create folder" in err and "Read-only file system" in err, err
    monkeypatch.setattr(paths.os, "access", lambda *a, **k: False)
    rc = cli.main(["run", str(path), "--no-progress", "--log", str(tmp_path / "x.mcap")])
    err = capsys.readouterr().err
    assert rc == 2 and "--log: cannot write into folder" in err, err
    assert not (tmp_path / "x.mcap").exists()


@pytest.mark.parametrize(
    ("content", "names"),
    [
        (b"time_s,position\n0,\xff\xfe\n", "not UTF-8"),
        (b"root:x:0:0:root:/root:/bin/bash\ndaemon:x:1:1\n", "line 1: the header must be"),
        (b"time_s,position\n0,0\n1,secret-token\n", "line 3, column 2: not a number"),
    ],
)
def test_a_bad_reference_csv_names_the_line_never_its_content(
    content: bytes, names: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "ref.csv").write_bytes(content)
    path = tmp_path / "csv.toml"
    step = 'kind = "step"\nposition = 1.0\nstart_s = 0.0\n'
    path.write_text(_edit(step, 'kind = "csv"\npath = "ref.csv"\n'))
    rc = cli.main(["run", str(path), "--no-progress", "--log", str(tmp_path / "x.mcap")])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert "reference.path" in err and names in err
    assert "root:x" not in err and "secret" not in err
    assert not (tmp_path / "x.mcap").exists()


def test_firmware_sim_shares_the_parser(tmp_path: Path) -> None:
    import subprocess

    path = tmp_path / "bad.toml"
    path.write_text(_edit("current_limit_A = 0.7", f"current_limit_A = {_BIG}"))
    proc = subprocess.run(
        [sys.executable, "-m", "firmware_sim", str(path), "-i", "virtual", "-c", "nowhere"],
        check=False, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert "drive.current_limit_A" in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
