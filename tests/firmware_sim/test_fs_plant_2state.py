"""PlantModel.advance_2state (the lockstep drives' per-period physics) against PlantModel.advance.

Exact float equality: the shortcut must give the general path's result bit for bit, for any state,
current, disturbance and span of whole cells, across the disturbance cache's block boundaries; and
refuse (False, nothing changed) where it does not apply.
"""

from __future__ import annotations

import functools

import pytest
from fs_support import make_config
from hypothesis import given, settings
from hypothesis import strategies as st

from dob_hil.config import Config
from firmware_sim.disturbance import Disturbance
from firmware_sim.plant import DISTURBANCE_BLOCK, PlantModel

NO_DESIGN = {"estimator": {}, "feedback": {}, "dob": {}}
DISTURBANCES: dict[str, list[dict[str, object]] | None] = {
    "none": None,
    "sine": [{"kind": "sine", "amplitude_A": 0.3, "frequency_hz": 37.0, "phase_rad": 0.4}],
    "mixed": [
        {"kind": "sine", "amplitude_A": 0.2, "frequency_hz": 5.0},
        {"kind": "step", "amplitude_A": -0.15, "start_s": 0.0123},
        {"kind": "noise", "std_A": 0.05, "seed": 7},
    ],
}
PLANT_3 = {
    "A": [[0.0, 1.0, 0.0], [0.0, -50.0, 3000.0], [0.0, 0.0, -2000.0]],
    "B": [[0.0], [0.0], [2000.0]],
    "C": [[1.0, 0.001, 0.0]],
    "state_names": None,
}

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
current = st.floats(-20.0, 20.0, allow_nan=False, allow_infinity=False)


@functools.cache
def _config(substeps: int, disturbance: str, three_states: bool = False) -> Config:
    sim: dict[str, object] = {"substeps": substeps, "disturbance": DISTURBANCES[disturbance]}
    plant: dict[str, object] = dict(PLANT_3) if three_states else {}
    return make_config(sim=sim, plant=plant, design=NO_DESIGN)


def _pair(substeps: int, disturbance: str, state: list[float]) -> tuple[PlantModel, PlantModel]:
    cfg = _config(substeps, disturbance)
    models = []
    for _ in range(2):
        dist = Disturbance(cfg.sim.disturbances, cfg.plant.period_s / substeps)
        models.append(PlantModel(cfg.plant, substeps, dist, state))
    return models[0], models[1]


@settings(max_examples=150, deadline=None)
@given(
    substeps=st.sampled_from([1, 3, 7, 10]),
    disturbance=st.sampled_from(sorted(DISTURBANCES)),
    state=st.lists(finite, min_size=2, max_size=2),
    # the first period: anywhere, or just before a disturbance block boundary
    start_period=st.one_of(
        st.integers(0, 50_000), st.integers(DISTURBANCE_BLOCK // 10 - 3, DISTURBANCE_BLOCK // 10)
    ),
    spans=st.lists(st.tuples(st.integers(0, 3), current), min_size=1, max_size=8),
)
def test_advance_2state_is_advance_bit_for_bit(
    substeps: int,
    disturbance: str,
    state: list[float],
    start_period: int,
    spans: list[tuple[int, float]],
) -> None:
    fast, general = _pair(substeps, disturbance, state)
    period_ns = fast.period_ns
    t_ns = start_period * period_ns
    for periods, current_A in spans:
        t1_ns = t_ns + periods * period_ns
        assert fast.advance_2state(t_ns, t1_ns, current_A)
        general.advance(t_ns, t1_ns, current_A)
        assert fast.state == general.state  # exact
        assert fast.position() == general.position()
        t_ns = t1_ns


@settings(max_examples=60, deadline=None)
@given(
    substeps=st.sampled_from([3, 10]),
    disturbance=st.sampled_from(sorted(DISTURBANCES)),
    state=st.lists(finite, min_size=2, max_size=2),
    cells=st.lists(st.tuples(st.integers(0, 25), current), min_size=1, max_size=8),
    start_cell=st.integers(0, 3 * DISTURBANCE_BLOCK),
)
def test_advance_2state_over_whole_cells(
    substeps: int,
    disturbance: str,
    state: list[float],
    cells: list[tuple[int, float]],
    start_cell: int,
) -> None:
    """Spans of whole cells that are not whole periods (the CiA 402 SYNC cycle may differ)."""
    fast, general = _pair(substeps, disturbance, state)
    period_ns = fast.period_ns  # a multiple of every substeps here: cells are whole ns
    assert period_ns % substeps == 0
    cell_ns = period_ns // substeps
    t_ns = start_cell * cell_ns
    for n, current_A in cells:
        t1_ns = t_ns + n * cell_ns
        assert fast.advance_2state(t_ns, t1_ns, current_A)
        general.advance(t_ns, t1_ns, current_A)
        assert fast.state == general.state
        t_ns = t1_ns


@pytest.mark.parametrize("offset_ns", [1, 999, 1000, 12_345])
def test_advance_2state_refuses_a_span_off_the_cell_grid(offset_ns: int) -> None:
    fast, _ = _pair(10, "sine", [0.1, -2.0])
    period_ns = fast.period_ns
    before = fast.state
    assert not fast.advance_2state(offset_ns, period_ns, 1.0)  # start inside a cell
    assert not fast.advance_2state(0, period_ns + offset_ns, 1.0)  # end inside a cell
    assert fast.state == before


def test_advance_2state_refuses_other_plant_orders() -> None:
    cfg = _config(5, "sine", three_states=True)
    plant = PlantModel(cfg.plant, 5, Disturbance(cfg.sim.disturbances, cfg.plant.period_s / 5), None)
    assert not plant.advance_2state(0, cfg.plant.period_ns, 0.5)
    assert plant.state == (0.0, 0.0, 0.0)


def test_advance_2state_runaway_matches_advance() -> None:
    """A state driven out of float range: the same infinities and NaNs as advance (by repr)."""
    fast, general = _pair(10, "sine", [1e308, 1e308])
    period_ns = fast.period_ns
    assert fast.advance_2state(0, 100 * period_ns, 1e308)
    general.advance(0, 100 * period_ns, 1e308)
    assert repr(fast.state) == repr(general.state)
    assert not all(abs(v) < float("inf") for v in fast.state)  # it did run away
