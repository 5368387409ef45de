"""References for every output (``[[reference.outputs]]``) and the vectorised ``block``.

``block(k_start, n)`` must be bit for bit ``at(k)`` for every k (it replaces per-sample calls in
``dob-hil replay --verify``): checked with hypothesis over step, sine and CSV references, single
and multi-output, compared through the raw float64 bits (so -0.0 against 0.0 counts).
"""

from __future__ import annotations

import json
import math
import textwrap
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dob_hil import cli
from dob_hil.config import Config, ReferenceConfig, parse_config_text
from dob_hil.control.reference import Reference, make_reference
from dob_hil.design import build_design
from dob_hil.design.tracking import tracking_map
from dob_hil.errors import ConfigError

# The 2x2 coupled plant of tests/design/conftest.py (two currents in, two positions out).
MIMO = """
[plant]
A = [[0.0, 1.0, 0.0, 0.0], [-40.0, -20.0, 40.0, 5.0], [0.0, 0.0, 0.0, 1.0], [30.0, 5.0, -30.0, -25.0]]
B = [[0.0, 0.0], [100.0, 10.0], [0.0, 0.0], [-5.0, 80.0]]
C = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
period_us = 1000.0
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

# A two-output plant whose map is dense (outputs are mixtures of the states): every x_ref entry
# sums terms of both outputs.
MIXED = """
[plant]
A = [[0.0, 1.0, 0.0, 0.0], [-40.0, -20.0, 40.0, 5.0], [0.0, 0.0, 0.0, 1.0], [30.0, 5.0, -30.0, -25.0]]
B = [[0.0, 0.0], [100.0, 10.0], [0.0, 0.0], [-5.0, 80.0]]
C = [[1.0, 0.0, 0.5, 0.0], [0.3, 0.0, 1.0, 0.0]]
period_us = 1000.0
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

PAPER_PERIOD_S = 300e-6


def _config(text: str, reference: str, base: Path | None = None) -> Config:
    source = None if base is None else base / "config.toml"
    return parse_config_text(textwrap.dedent(text) + textwrap.dedent(reference), source=source)


def _bits(a: npt.ArrayLike) -> npt.NDArray[np.uint64]:
    return np.ascontiguousarray(np.asarray(a, dtype=np.float64)).view(np.uint64)


def _assert_block_is_at(ref: Reference, k_start: int, n: int) -> None:
    block = ref.block(k_start, n)
    n_states = len(ref.at(k_start))
    rows = np.array([ref.at(k) for k in range(k_start, k_start + n)], dtype=np.float64).reshape(n, n_states)
    assert block.dtype == np.float64
    assert block.shape == rows.shape
    np.testing.assert_array_equal(_bits(block), _bits(rows))


def _map(text: str) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    t = tracking_map(build_design(parse_config_text(textwrap.dedent(text))))
    return t.Nx, t.Nv


@pytest.fixture(scope="module")
def mimo_map() -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    return _map(MIMO)


@pytest.fixture(scope="module")
def mixed_map() -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    return _map(MIXED)


def _csv(tmp_path: Path, name: str, rows: str) -> Path:
    path = tmp_path / name
    path.write_text(rows)
    return path


# ---------------------------------------------------------------------------------------------
# The 2x2 design's state map, and each output's command
# ---------------------------------------------------------------------------------------------
def test_the_2x2_state_map_puts_each_position_state_at_its_output(
    mimo_map: tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]],
) -> None:
    Nx, Nv = mimo_map
    assert Nx.shape == Nv.shape == (4, 2)
    np.testing.assert_array_equal(Nx, [[1.0, 0.0], [0.0, 0.0], [0.0, 1.0], [0.0, 0.0]])
    np.testing.assert_array_equal(Nv, [[0.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.0, 1.0]])


def test_per_output_step_and_sine_on_the_2x2_plant(
    mimo_map: tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]],
) -> None:
    cfg = _config(
        MIMO,
        """
        [[reference.outputs]]
        kind = "step"
        position = 0.5
        start_s = 0.01
        [[reference.outputs]]
        kind = "sine"
        amplitude = 0.2
        frequency_hz = 3.0
        offset = 0.1
        """,
    )
    assert len(cfg.reference.outputs) == 2
    ref = make_reference(cfg.reference, 4, cfg.plant.period_s, state_map=mimo_map)
    w = 2.0 * math.pi * 3.0
    for k in (0, 9, 10, 11, 250, 999):
        t = k * 1e-3
        p1 = 0.5 if k >= 10 else 0.0
        p2 = 0.1 + 0.2 * math.sin(w * t)
        v2 = 0.2 * w * math.cos(w * t)
        np.testing.assert_allclose(ref.at(k), [p1, 0.0, p2, v2], rtol=0, atol=1e-12)


def test_per_output_csv(
    tmp_path: Path, mimo_map: tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]
) -> None:
    _csv(tmp_path, "a.csv", "time_s,position\n0.0,0.0\n0.01,1.0\n")
    _csv(tmp_path, "b.csv", "time_s,position,velocity\n0.0,2.0,0.0\n0.02,0.0,-100.0\n")
    cfg = _config(
        MIMO,
        """
        [[reference.outputs]]
        kind = "csv"
        path = "a.csv"
        [[reference.outputs]]
        kind = "csv"
        path = "b.csv"
        """,
        base=tmp_path,
    )
    ref = make_reference(cfg.reference, 4, cfg.plant.period_s, state_map=mimo_map)
    np.testing.assert_allclose(ref.at(5), [0.5, 100.0, 1.5, -25.0], atol=1e-12)
    np.testing.assert_allclose(ref.at(1000), [1.0, 0.0, 0.0, 0.0], atol=0)  # held, rate 0 after the end


def test_a_dense_map_sums_every_output(
    mixed_map: tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]],
) -> None:
    Nx, Nv = mixed_map
    assert np.count_nonzero(Nx) > 2  # both outputs reach the same states
    cfg = _config(
        MIXED,
        """
        [[reference.outputs]]
        kind = "sine"
        amplitude = 0.4
        frequency_hz = 2.0
        [[reference.outputs]]
        position = -0.3
        """,
    )
    ref = make_reference(cfg.reference, 4, cfg.plant.period_s, state_map=mixed_map)
    C = np.array([[1.0, 0.0, 0.5, 0.0], [0.3, 0.0, 1.0, 0.0]])
    w = 4.0 * math.pi
    for k in (0, 17, 123, 480):
        r = np.array([0.4 * math.sin(w * k * 1e-3), -0.3])
        r_dot = np.array([0.4 * w * math.cos(w * k * 1e-3), 0.0])
        x_ref = np.asarray(ref.at(k))
        np.testing.assert_allclose(x_ref, Nx @ r + Nv @ r_dot, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(C @ x_ref, r, rtol=1e-9, atol=1e-12)  # every output at its reference


def test_legacy_reference_is_bit_for_bit_and_holds_the_other_outputs_at_zero(
    mimo_map: tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]],
) -> None:
    """Without [[reference.outputs]]: output 0 from [reference], output 1 at zero, exactly as the
    single-column formula (no sum with the other output's zero terms)."""
    cfg = _config(MIMO, '[reference]\nkind = "sine"\namplitude = -0.7\nfrequency_hz = 5.0\n')
    assert cfg.reference.outputs == ()
    ref = make_reference(cfg.reference, 4, cfg.plant.period_s, state_map=mimo_map)
    w = 2.0 * math.pi * 5.0
    for k in range(0, 400, 7):
        wt = w * (k * 1e-3)
        expected = (-0.7 * math.sin(wt), -0.7 * w * math.cos(wt))
        assert ref.at(k) == (expected[0], expected[1], 0.0, 0.0)


def test_one_table_per_output_equals_the_scalar_reference_bit_for_bit() -> None:
    paper_map = (np.array([[1.0], [0.0]]), np.array([[0.0], [1.0]]))
    scalar = ReferenceConfig(kind="sine", amplitude=1.3, frequency_hz=7.0, offset=0.25)
    listed = ReferenceConfig(outputs=(scalar,))
    a = make_reference(scalar, 2, PAPER_PERIOD_S, state_map=paper_map)
    b = make_reference(listed, 2, PAPER_PERIOD_S, state_map=paper_map)
    legacy = make_reference(scalar, 2, PAPER_PERIOD_S)
    listed_legacy = make_reference(listed, 2, PAPER_PERIOD_S)  # no map: the legacy convention too
    for k in range(0, 5000, 37):
        assert a.at(k) == b.at(k) == legacy.at(k) == listed_legacy.at(k)


def test_several_outputs_need_a_state_map() -> None:
    two = ReferenceConfig(outputs=(ReferenceConfig(), ReferenceConfig()))
    with pytest.raises(ConfigError, match=r"reference\.outputs"):
        make_reference(two, 4, 1e-3)
    with pytest.raises(ConfigError, match=r"reference\.outputs"):
        make_reference(two, 2, 1e-3, state_map=(np.eye(2)[:, :1], np.eye(2)[:, :1]))


# ---------------------------------------------------------------------------------------------
# block(k_start, n): bit for bit at(k)
# ---------------------------------------------------------------------------------------------
_finite = st.floats(min_value=-1e3, max_value=1e3, allow_nan=False, allow_subnormal=False)
_starts = st.integers(min_value=0, max_value=10**7)
_lengths = st.integers(min_value=0, max_value=300)
_periods = st.sampled_from([300e-6, 1e-3, 125e-6, 1.0 / 3.0e3])
_single_maps = st.sampled_from(
    [
        None,
        (np.array([[1.0], [0.0]]), np.array([[0.0], [1.0]])),
        (np.array([[1.0], [0.0], [-0.4], [0.0]]), np.array([[0.0], [1.0], [0.0], [2.5e-3]])),
    ]
)


def _step(draw: st.DrawFn) -> ReferenceConfig:
    return ReferenceConfig(
        kind="step", position=draw(_finite), start_s=draw(st.floats(min_value=0.0, max_value=20.0))
    )


def _sine(draw: st.DrawFn) -> ReferenceConfig:
    return ReferenceConfig(
        kind="sine",
        amplitude=draw(_finite),
        frequency_hz=draw(st.floats(min_value=0.0, max_value=400.0)),
        offset=draw(_finite),
    )


@st.composite
def _signal_configs(draw: st.DrawFn) -> ReferenceConfig:
    return _step(draw) if draw(st.booleans()) else _sine(draw)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cfg=_signal_configs(), k_start=_starts, n=_lengths, period_s=_periods, state_map=_single_maps)
def test_block_is_at_single_output(
    cfg: ReferenceConfig,
    k_start: int,
    n: int,
    period_s: float,
    state_map: tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]] | None,
) -> None:
    n_states = 2 if state_map is None else state_map[0].shape[0]
    _assert_block_is_at(make_reference(cfg, n_states, period_s, state_map=state_map), k_start, n)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    a=_signal_configs(),
    b=_signal_configs(),
    k_start=_starts,
    n=_lengths,
    dense=st.booleans(),
    data=st.data(),
)
def test_block_is_at_multi_output(
    a: ReferenceConfig,
    b: ReferenceConfig,
    k_start: int,
    n: int,
    dense: bool,
    data: st.DataObject,
) -> None:
    if dense:
        Nx = np.array([[1.0, -0.5], [0.0, 0.0], [0.3, 1.0], [0.0, 0.0]])
        Nv = np.array([[0.0, 0.0], [1.0, -0.5], [0.0, 0.0], [0.3, 1.0]])
    else:
        Nx = np.array([[1.0, 0.0], [0.0, 0.0], [0.0, 1.0], [0.0, 0.0]])
        Nv = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.0, 1.0]])
    period_s = data.draw(_periods)
    ref = make_reference(ReferenceConfig(outputs=(a, b)), 4, period_s, state_map=(Nx, Nv))
    _assert_block_is_at(ref, k_start, n)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    times=st.lists(st.integers(min_value=0, max_value=20_000), min_size=1, max_size=30, unique=True),
    values=st.lists(_finite, min_size=60, max_size=60),
    with_velocity=st.booleans(),
    k_start=st.integers(min_value=0, max_value=8000),
    n=_lengths,
    multi=st.booleans(),
)
def test_block_is_at_csv(
    tmp_path_factory: pytest.TempPathFactory,
    times: list[int],
    values: list[float],
    with_velocity: bool,
    k_start: int,
    n: int,
    multi: bool,
) -> None:
    rows = [
        f"{t * 1e-4!r},{values[i]!r}" + (f",{values[30 + i]!r}" if with_velocity else "")
        for i, t in enumerate(sorted(times))
    ]
    header = "time_s,position" + (",velocity" if with_velocity else "")
    path = tmp_path_factory.mktemp("csv") / "ref.csv"
    path.write_text(header + "\n" + "\n".join(rows) + "\n")
    csv_cfg = ReferenceConfig(kind="csv", csv_path=path)
    if multi:
        Nx = np.array([[1.0, 0.2], [0.0, 0.0], [0.0, 1.0], [0.0, 0.0]])
        Nv = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.0, 1.0]])
        sine = ReferenceConfig(kind="sine", amplitude=0.3, frequency_hz=3.0)
        ref = make_reference(ReferenceConfig(outputs=(sine, csv_cfg)), 4, 1e-3, state_map=(Nx, Nv))
    else:
        ref = make_reference(csv_cfg, 2, 1e-3)
    _assert_block_is_at(ref, k_start, n)


def test_block_of_a_long_paper_sine_run_is_at() -> None:
    """One long block (a 10 s run at 300 us) of the paper's sine, legacy and mapped."""
    cfg = ReferenceConfig(kind="sine", amplitude=1.0, frequency_hz=1.0)
    for state_map in (None, (np.array([[1.0], [0.0]]), np.array([[0.0], [1.0]]))):
        _assert_block_is_at(make_reference(cfg, 2, PAPER_PERIOD_S, state_map=state_map), 0, 33_334)


# ---------------------------------------------------------------------------------------------
# Through a lockstep run and replay --verify
# ---------------------------------------------------------------------------------------------
def test_a_run_with_one_reference_table_logs_the_scalar_reference_and_verifies(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The paper's sine commanded through [[reference.outputs]] runs exactly as through
    [reference]; replay --verify rebuilds its x_ref from the logged config."""
    from dob_hil.analysis.loaded import load_log
    from dob_hil.analysis.replay import verify
    from dob_hil.log import read_log
    from dob_hil.loop.session import RunOptions, run_session
    from dob_hil.scenarios import scenario_path

    paper = scenario_path("paper-sine").read_text()
    start = paper.index("[reference]\n")
    end = paper.index("\n[", start + 1) + 1
    table = paper[start:end]
    listed = paper[:start] + table.replace("[reference]", "[[reference.outputs]]") + paper[end:]
    logs = []
    for i, text in enumerate((paper, listed)):
        cfg = parse_config_text(text)
        log_path = tmp_path / f"run{i}.mcap"
        run_session(cfg, RunOptions(log_path=log_path, duration_s=0.05))
        logs.append(read_log(log_path).samples)
    assert len(logs[0]) == len(logs[1]) > 100
    np.testing.assert_array_equal(_bits(logs[0]["x_ref"]), _bits(logs[1]["x_ref"]))
    np.testing.assert_array_equal(_bits(logs[0]["u_cmd_a"]), _bits(logs[1]["u_cmd_a"]))
    result = verify(load_log(tmp_path / "run1.mcap"))
    assert result.identical, result.first_mismatches
    assert "x_ref" in result.fields
    assert cli.main(["replay", "--verify", "--json", str(tmp_path / "run1.mcap")]) == 0  # the fast path
    out = json.loads(capsys.readouterr().out)
    assert out["identical"] and "x_ref" in out["fields"]
