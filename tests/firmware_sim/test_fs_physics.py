"""Plant physics against independent solutions: closed form, scipy lsim and solve_ivp."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import scipy.integrate
import scipy.signal
from fs_support import make_config
from plants import A_3, B_3, C_3, PLANT_3

from dob_hil.errors import ConfigError
from firmware_sim.disturbance import Disturbance
from firmware_sim.plant import PlantModel, zoh

A_DAMP = 128.59
B_GAIN = 2.1484e4


NO_DESIGN = {"estimator": {}, "feedback": {}, "dob": {}}  # the paper's gains fit only its 2-state plant


def plant_model(
    substeps: int = 10, disturbances: list[dict[str, object]] | None = None, **plant: object
) -> PlantModel:
    sim: dict[str, object] = {"substeps": substeps, "disturbance": disturbances}
    cfg = make_config(sim=sim, plant=dict(plant), design=NO_DESIGN)
    dist = Disturbance(cfg.sim.disturbances, cfg.plant.period_s / substeps)
    return PlantModel(cfg.plant, substeps, dist, cfg.sim.initial_state)


def double_integrator_with_damping(u_A: float, t_s: float) -> tuple[float, float]:
    """x1' = x2, x2' = -a x2 + b u from rest, u constant: the exact solution."""
    e = math.exp(-A_DAMP * t_s)
    v = B_GAIN * u_A / A_DAMP * (1.0 - e)
    x = B_GAIN * u_A / A_DAMP * (t_s - (1.0 - e) / A_DAMP)
    return x, v


def test_zoh_matches_the_paper_and_the_closed_form() -> None:
    A = np.array([[0.0, 1.0], [0.0, -A_DAMP]])
    B = np.array([[0.0], [B_GAIN]])
    Phi, Gam = zoh(A, B, 300e-6)
    # the paper's Phi and Gam (4-5 significant digits)
    np.testing.assert_allclose(Phi, [[1.0, 2.9429e-4], [0.0, 9.6216e-1]], rtol=2e-4, atol=1e-9)
    np.testing.assert_allclose(Gam[:, 0], [9.5445e-4, 6.3224], rtol=2e-4)
    # and the closed form of the same integral
    x, v = double_integrator_with_damping(1.0, 300e-6)
    np.testing.assert_allclose(Gam[:, 0], [x, v], rtol=1e-12)


def test_constant_current_is_exact_whatever_the_substeps() -> None:
    for substeps in (1, 3, 10):
        plant = plant_model(substeps)
        t_ns = 0
        for _ in range(500):  # 0.15 s
            plant.advance(t_ns, t_ns + 300_000, 0.25)
            t_ns += 300_000
        x, v = double_integrator_with_damping(0.25, t_ns * 1e-9)
        np.testing.assert_allclose(plant.state, (x, v), rtol=1e-10)
        assert plant.position() == plant.state[0]


def test_piecewise_current_matches_lsim() -> None:
    """A current that changes every period: the drive integrates exactly what ZOH lsim computes."""
    rng = np.random.default_rng(3)
    currents = rng.uniform(-0.7, 0.7, 200)
    plant = plant_model(substeps=4)
    states = []
    for k, u in enumerate(currents):
        plant.advance(k * 300_000, (k + 1) * 300_000, float(u))
        states.append(plant.state)
    sys_c = scipy.signal.StateSpace([[0.0, 1.0], [0.0, -A_DAMP]], [[0.0], [B_GAIN]], [[1.0, 0.0]], [[0.0]])
    sys_d = sys_c.to_discrete(300e-6, method="zoh")
    _, _, x = scipy.signal.dlsim(sys_d, currents[:, None], x0=[0.0, 0.0])
    np.testing.assert_allclose(np.array(states)[:-1], x[1:], rtol=1e-9, atol=1e-12)


def _reference_with_sine(t_end_s: float, amplitude_A: float, freq_hz: float, u_A: float) -> np.ndarray:
    w = 2 * math.pi * freq_hz

    def f(t: float, x: np.ndarray) -> list[float]:
        return [x[1], -A_DAMP * x[1] + B_GAIN * (u_A + amplitude_A * math.sin(w * t))]

    sol = scipy.integrate.solve_ivp(f, (0.0, t_end_s), [0.0, 0.0], method="DOP853", rtol=1e-13, atol=1e-15)
    return np.asarray(sol.y[:, -1])


def _error_with_sine(substeps: int, periods: int) -> float:
    plant = plant_model(substeps, [{"kind": "sine", "amplitude_A": 0.2, "frequency_hz": 40.0}])
    for k in range(periods):
        plant.advance(k * 300_000, (k + 1) * 300_000, 0.05)
    ref = _reference_with_sine(periods * 300e-6, 0.2, 40.0, 0.05)
    return float(np.max(np.abs(np.array(plant.state) - ref) / np.abs(ref)))


def test_sine_disturbance_matches_solve_ivp_and_converges_second_order() -> None:
    errors = [_error_with_sine(s, 200) for s in (2, 4, 8)]
    wh = 2 * math.pi * 40.0 * 300e-6 / 8
    assert errors[-1] < wh**2 / 12  # the midpoint rule's error scale for a sine held over h
    # midpoint hold: halving the sub-step divides the error by ~4
    for coarse, fine in itertools_pairs(errors):
        assert 3.0 < coarse / fine < 5.0, errors


def itertools_pairs(values: list[float]) -> list[tuple[float, float]]:
    return list(itertools.pairwise(values))


def test_split_inside_a_substep_matches_the_continuous_solution() -> None:
    """Real time: a current change at an arbitrary (whole-us) instant inside a sub-step is exact."""
    plant = plant_model(substeps=10)
    t_switch_ns = 3 * 300_000 + 47_000 + 13_000  # inside the 3rd cell of period 3
    plant.advance(0, t_switch_ns, 0.3)
    plant.advance(t_switch_ns, 10 * 300_000, -0.1)
    t1, t2 = t_switch_ns * 1e-9, 10 * 300e-6

    def f(t: float, x: np.ndarray) -> list[float]:
        return [x[1], -A_DAMP * x[1] + B_GAIN * (0.3 if t < t1 else -0.1)]

    a = scipy.integrate.solve_ivp(f, (0, t1), [0, 0], method="DOP853", rtol=1e-13, atol=1e-16)
    b = scipy.integrate.solve_ivp(f, (t1, t2), a.y[:, -1], method="DOP853", rtol=1e-13, atol=1e-16)
    np.testing.assert_allclose(plant.state, b.y[:, -1], rtol=1e-9)


def test_many_small_pieces_equal_one_span() -> None:
    """Integrating in arbitrary pieces (the real-time clock) gives the same state as one span."""
    dist = [{"kind": "sine", "amplitude_A": 0.2, "frequency_hz": 4.0}]
    whole = plant_model(10, dist)
    pieces = plant_model(10, dist)
    whole.advance(0, 3_000_000, 0.1)
    cuts = [0, 17_000, 30_000, 31_000, 299_000, 300_000, 1_234_000, 2_999_000, 3_000_000]
    for a, b in itertools_pairs([float(c) for c in cuts]):
        pieces.advance(int(a), int(b), 0.1)
    np.testing.assert_allclose(pieces.state, whole.state, rtol=1e-10)


def test_general_state_dimension_matches_lsim() -> None:
    """A 3-state plant (current loop lag + damped axis) through the generic path; C mixes states."""
    A, B, C = A_3, B_3, C_3
    plant = plant_model(5, None, **PLANT_3)
    u = [0.2] * 50 + [-0.1] * 50
    for k, uk in enumerate(u):
        plant.advance(k * 300_000, (k + 1) * 300_000, uk)
    sys_d = scipy.signal.StateSpace(A, B, C, [[0.0]]).to_discrete(300e-6, method="zoh")
    _, _, x = scipy.signal.dlsim(sys_d, np.array(u)[:, None])
    final = sys_d.A @ x[-1] + sys_d.B[:, 0] * u[-1]
    np.testing.assert_allclose(plant.state, final, rtol=1e-9)
    assert plant.position() == pytest.approx(C[0][0] * final[0] + C[0][1] * final[1], rel=1e-12)


def test_initial_state_is_used() -> None:
    plant = plant_model(10, None)
    cfg = make_config(sim={"initial_state": [0.5, 2.0]})
    plant = PlantModel(cfg.plant, 10, Disturbance((), 30e-6), cfg.sim.initial_state)
    assert plant.state == (0.5, 2.0)
    plant.advance(0, 300_000, 0.0)
    v = 2.0 * math.exp(-A_DAMP * 300e-6)
    x = 0.5 + 2.0 / A_DAMP * (1 - math.exp(-A_DAMP * 300e-6))
    np.testing.assert_allclose(plant.state, (x, v), rtol=1e-12)


@pytest.mark.parametrize(
    ("plant", "field"),
    [
        ({"B": [[0.0, 0.0], [1.0, 1.0]], "input_names": None}, "plant.B"),
        ({"C": [[1.0, 0.0], [0.0, 1.0]], "output_names": None}, "plant.C"),
    ],
)
def test_refuses_more_than_one_input_or_output(plant: dict[str, object], field: str) -> None:
    cfg = make_config(plant=plant, design=NO_DESIGN)
    with pytest.raises(ConfigError) as info:
        PlantModel(cfg.plant, 10, Disturbance((), 30e-6))
    assert info.value.field == field
    assert "single-axis" in str(info.value)
