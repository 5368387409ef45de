"""PlantModel.advance_2state (the lockstep drives' per-period physics) against PlantModel.advance.

Exact float equality: the shortcut must give the general path's result bit for bit, for any state,
current, disturbance and span of whole cells, across the disturbance caches' block boundaries; and
refuse (False, nothing changed) where it does not apply. The whole-period update both take (the
cells composed) is checked against the cell-by-cell recurrence, written out here, and against the
exact discretisation over a period.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from fs_support import make_config
from hypothesis import given, settings
from hypothesis import strategies as st
from plants import PLANT_3

from dob_hil.config import Config
from firmware_sim.actuator import CurrentPath
from firmware_sim.disturbance import Disturbance
from firmware_sim.plant import DISTURBANCE_BLOCK, PlantModel, periods_per_block, zoh

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
        st.integers(0, 50_000),
        st.integers(DISTURBANCE_BLOCK // 10 - 3, DISTURBANCE_BLOCK // 10),
        # the per-period disturbance cache's block boundaries, for each substeps drawn
        st.sampled_from(
            [periods_per_block(s) * m - d for s in (1, 3, 7, 10) for m in (1, 7) for d in range(4)]
        ),
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


def _cell_by_cell(model: PlantModel, state: list[float], j0: int, j1: int, u: float) -> list[float]:
    """Cells j0 .. j1-1 one by one (x+ = Phi_h x + Gam_h (u + w_j), w_j at the cell's midpoint)."""
    phi, gam = zoh(model._A, model._B, model.cell_s)
    dist = model._disturbance
    x = np.asarray(state, dtype=np.float64)
    for j in range(j0, j1):
        w = 0.0 if dist.is_zero else float(dist.values_A(np.array([(j + 0.5) * model.cell_s]))[0])
        x = phi @ x + gam[:, 0] * (u + w)
    return [float(v) for v in x]


@pytest.mark.parametrize("disturbance", sorted(DISTURBANCES))
@pytest.mark.parametrize("substeps", [1, 4, 10])
def test_whole_periods_equal_the_cell_recurrence_to_rounding(disturbance: str, substeps: int) -> None:
    """Periods across a block boundary of the per-period disturbance cache, with a current
    changing every period: the composed update stays within rounding of cell-by-cell updates."""
    plant, _ = _pair(substeps, disturbance, [0.02, -1.5])
    period_ns = plant.period_ns
    rng = np.random.default_rng(substeps)
    first = periods_per_block(substeps) - 20
    plant.advance_2state(0, first * period_ns, 0.0)  # to the start (checked below from there)
    x = plant.state
    ref = list(x)
    for k in range(first, first + 40):
        u = float(rng.uniform(-3.0, 3.0))
        assert plant.advance_2state(k * period_ns, (k + 1) * period_ns, u)
        ref = _cell_by_cell(plant, ref, k * substeps, (k + 1) * substeps, u)
        for got, want in zip(plant.state, ref, strict=True):
            assert got == pytest.approx(want, rel=1e-11, abs=1e-12 * (1.0 + abs(want)))


def test_period_matrices_are_the_exact_discretisation_over_a_period() -> None:
    """Phi_h^S and sum_i Phi_h^i Gam_h (built by the cell recurrence) against expm over Ts."""
    plant, _ = _pair(10, "none", [0.0, 0.0])
    assert plant._p2 is not None
    a00, a01, a10, a11, b0, b1 = plant._p2
    phi, gam = zoh(plant._A, plant._B, plant.period_ns * 1e-9)
    np.testing.assert_allclose([[a00, a01], [a10, a11]], phi, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose([b0, b1], gam[:, 0], rtol=1e-12)


def test_a_moved_disturbance_origin_drops_the_period_cache() -> None:
    """disturbance_changed: the next period uses the new origin's disturbance (as a fresh model)."""
    moved, _ = _pair(10, "sine", [0.0, 0.0])
    period_ns = moved.period_ns
    assert moved.advance_2state(0, period_ns, 0.0)  # caches block 0 with origin 0
    moved._disturbance.origin_s = 0.0017
    moved.disturbance_changed()
    fresh, _ = _pair(10, "sine", [0.0, 0.0])
    fresh._disturbance.origin_s = 0.0017
    fresh._x = list(moved.state)
    assert moved.advance_2state(period_ns, 2 * period_ns, 0.5)
    assert fresh.advance_2state(period_ns, 2 * period_ns, 0.5)
    assert moved.state == fresh.state


def test_a_cache_load_stays_a_cell_block_whatever_the_substeps() -> None:
    """A load of the per-period cache covers at most one cell block (or one period): a real-time
    tick pays it between two deadlines, and substeps may be 10,000."""
    for substeps in (1, 3, 10, 4096, 4097, 10_000):
        n = periods_per_block(substeps)
        assert n >= 1
        assert n * substeps <= max(DISTURBANCE_BLOCK, substeps)
    plant, _ = _pair(10, "sine", [0.0, 0.0])
    assert plant.advance_2state(0, plant.period_ns, 0.0)
    assert len(plant._d0) == periods_per_block(10)


def test_cells_before_time_zero_are_integrated() -> None:
    """Cells of negative time (block -1) are cells like any other: not skipped."""
    plant, reference = _pair(10, "sine", [0.0, 1.0])
    period_ns = plant.period_ns
    plant.advance(-3 * period_ns // 10, 0, 1.0)  # three whole cells before t = 0
    assert plant.state != (0.0, 1.0)
    fresh, _ = _pair(10, "none", [0.0, 1.0])  # the sine starts at 0: nothing before it
    fresh.advance(-3 * period_ns // 10, 0, 1.0)
    assert plant.state == fresh.state
    assert reference.state == (0.0, 1.0)


def test_noise_whose_origin_moved_integrates_the_cells_before_it() -> None:
    """An ODrive's disturbance starts at the first closed-loop entry (period 3 here): the noise's
    cache block still holds cells before that origin, which are 0 (they raised IndexError)."""
    from firmware_sim.odrive.core import StartAtEnable

    cfg = _config(10, "mixed")
    period_ns = cfg.plant.period_ns
    dist = StartAtEnable(Disturbance(cfg.sim.disturbances, cfg.plant.period_s / 10))
    fast = PlantModel(cfg.plant, 10, dist, [0.0, 0.0])  # type: ignore[arg-type]
    assert fast.advance_2state(0, 3 * period_ns, 0.0)
    dist.start(3 * period_ns)  # as OdriveCore does (no cache was filled while it was zero)
    assert fast.advance_2state(3 * period_ns, 4 * period_ns, 0.1)
    assert all(abs(v) < float("inf") for v in fast.state)
    noise = Disturbance(cfg.sim.disturbances, cfg.plant.period_s / 10)
    noise.origin_s = 0.5
    values = noise.values_A(np.array([0.0, 0.25, 0.5, 0.75]))
    assert values[0] == values[1] == 0.0
    assert values[3] == noise.value_A(0.75)


# --- CurrentPath.advance_held: the per-period common case of every drive -------------------------
def test_advance_held_applies_the_due_change_then_advances_one_period() -> None:
    fast, general = _pair(10, "sine", [0.1, -2.0])
    period_ns = fast.period_ns
    path = CurrentPath()
    path.schedule(5 * period_ns, 0.7)  # the change the last period scheduled, due at the start
    assert path.advance_held(fast, 5 * period_ns, 6 * period_ns)
    general.advance(5 * period_ns, 6 * period_ns, 0.7)
    assert path.held_A == 0.7 and path.pending == 0
    assert fast.state == general.state  # bit for bit


def test_advance_held_leaves_the_plant_to_the_caller_while_a_change_is_pending() -> None:
    fast, _ = _pair(10, "sine", [0.1, -2.0])
    period_ns = fast.period_ns
    path = CurrentPath()
    path.schedule(0, 0.2)
    path.schedule(period_ns // 2, 0.4)  # due inside the period: integrated change by change
    before = fast.state
    assert not path.advance_held(fast, 0, period_ns)
    assert fast.state == before and path.held_A == 0.2 and path.next_change_ns() == period_ns // 2


def test_advance_held_on_a_three_state_plant_takes_the_general_advance() -> None:
    cfg = _config(5, "sine", three_states=True)
    plants = [
        PlantModel(cfg.plant, 5, Disturbance(cfg.sim.disturbances, cfg.plant.period_s / 5), None)
        for _ in range(2)
    ]
    path = CurrentPath()
    path.held_A = 0.3
    assert path.advance_held(plants[0], 0, 3 * cfg.plant.period_ns)
    plants[1].advance(0, 3 * cfg.plant.period_ns, 0.3)
    assert plants[0].state == plants[1].state and plants[0].state != (0.0, 0.0, 0.0)
