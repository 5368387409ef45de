"""S and T at the plant output and the disturbance response, against an independent python-control
interconnection of the run-time controller equations; Theorem 1's eigenvalue split; margins."""

from __future__ import annotations

import math

import control
import numpy as np
import pytest

from dob_hil.design import Design, sensitivity_response
from dob_hil.design.dob import dc_estimate_gain
from dob_hil.design.linalg import frequency_grid_hz
from dob_hil.design.loops import design_loop_response, loop_at_a_time
from dob_hil.design.margins import loop_margins
from dob_hil.design.theorem1 import dob_matrix, feedback_matrix

from .helpers import block, runtime_interconnection, simulate_runtime, sub_system

CASES = [(name, dob) for name in ("paper", "mimo", "delay") for dob in (True, False)]


def _omega(design: Design, points: int = 60) -> np.ndarray:
    return 2 * math.pi * frequency_grid_hz(design.period_ns, points, decades=4.0)


@pytest.mark.parametrize(("name", "dob"), CASES)
def test_S_plus_T_is_identity(designs: dict[str, Design], name: str, dob: bool) -> None:
    d = designs[name]
    S, T = sensitivity_response(d, _omega(d, 300), dob)
    p = d.n_outputs
    assert S.shape == T.shape == (300, p, p)
    np.testing.assert_allclose(S + T, np.broadcast_to(np.eye(p), S.shape), atol=1e-9)


@pytest.mark.parametrize(("name", "dob"), CASES)
def test_S_T_and_disturbance_response_match_the_python_control_interconnection(
    designs: dict[str, Design], name: str, dob: bool
) -> None:
    d = designs[name]
    w = _omega(d)
    cl = runtime_interconnection(d, dob)
    G = cl(np.exp(1j * w * d.period_s))
    S, T = sensitivity_response(d, w, dob)
    S_ref = block(G, cl, "y", "d")  # output disturbance -> measured output
    T_ref = -block(G, cl, "yp", "d")  # output disturbance -> -(plant output)
    np.testing.assert_allclose(S, S_ref, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(T, T_ref, rtol=1e-7, atol=1e-9)
    r = design_loop_response(d, w, dob)
    np.testing.assert_allclose(r.disturbance, block(G, cl, "y", "w"), rtol=1e-7, atol=1e-12)


@pytest.mark.parametrize(("name", "dob"), CASES)
def test_closed_loop_eigenvalues_are_feedback_and_dob_eigenvalues(
    designs: dict[str, Design], name: str, dob: bool
) -> None:
    """Theorem 1: eig(closed loop) = eig(Phi - Gam Kc) with eig(Phi - Phi Lc C - Gam Kdist Lc C)."""
    d = designs[name]
    Kdist = d.Kdist if dob else np.zeros_like(d.Kdist)
    cl = runtime_interconnection(d, dob)
    got = np.linalg.eigvals(cl.A)
    want = np.concatenate(
        [
            np.linalg.eigvals(feedback_matrix(d.Phi, d.Gam, d.Kc)),
            np.linalg.eigvals(dob_matrix(d.Phi, d.Gam, d.C, d.Lc, Kdist)),
        ]
    )
    assert got.size == want.size
    # Match each expected eigenvalue to the nearest remaining one (multiple eigenvalues at 0 for the
    # delay line are defective, so compare with a tolerance that allows their O(eps^(1/k)) spread).
    remaining = list(got)
    for ev in want:
        j = int(np.argmin([abs(ev - g) for g in remaining]))
        assert abs(ev - remaining.pop(j)) < 1e-5
    assert max(abs(got)) < 1.0


def test_time_domain_run_time_loop_settles_to_the_dc_disturbance_estimate(designs: dict[str, Design]) -> None:
    """A constant input disturbance: -u_dist converges to Q(1) w, y to the DC of S Pw."""
    d = designs["paper"]
    hist = simulate_runtime(d, np.full((10_000, 1), 0.2), dob_enabled=True)
    Q1 = dc_estimate_gain(d.Phi, d.Gam, d.Gam_w, d.C, d.Lc, Kdist=d.Kdist)
    np.testing.assert_allclose(-hist["u_dist"][-1], Q1 @ [0.2], rtol=1e-6)
    # The paper's Kdist gives a DOB loop DC gain of ~1, so about half of a slow disturbance is estimated.
    assert 0.49 < float(Q1[0, 0]) < 0.52
    hist_off = simulate_runtime(d, np.full((10_000, 1), 0.2), dob_enabled=False)
    ratio = hist["y"][-1, 0] / hist_off["y"][-1, 0]
    np.testing.assert_allclose(ratio, 1.0 - Q1[0, 0], rtol=1e-6)


def test_margins_agree_with_python_control_on_the_loop_broken_at_the_plant_input(
    designs: dict[str, Design],
) -> None:
    d = designs["paper"]
    w = 2 * math.pi * frequency_grid_hz(d.period_ns, 3000)
    for dob in (True, False):
        mine = loop_margins(lambda x, dob=dob: loop_at_a_time(design_loop_response(d, x, dob).Si, 0), w)
        cl = runtime_interconnection(d, dob, open_at_plant_input=True)
        L = -sub_system(cl, "u", "uin")  # the loop: plant input -> ... -> -(controller output)
        gm, pm, _, wpc, wgc, _ = control.stability_margins(L)
        assert mine.gain_margin_db is not None and mine.phase_margin_deg is not None
        assert mine.gain_margin_db == pytest.approx(20 * math.log10(gm), abs=0.01)
        assert mine.phase_margin_deg == pytest.approx(pm, abs=0.01)
        assert mine.gain_crossover_hz == pytest.approx(wpc / (2 * math.pi), rel=1e-4)
        assert mine.phase_crossover_hz == pytest.approx(wgc / (2 * math.pi), rel=1e-4)


def test_kdist_reaches_the_loop_only_through_kdist_lc(designs: dict[str, Design]) -> None:
    """Adding to Kdist anything in the left null space of Lc leaves S unchanged."""
    d = designs["paper"]
    null = np.array([[0.5, -0.75]])  # null @ Lc = 0.5 * 0.75 - 0.75 * 0.5 = 0
    assert abs(float((null @ d.Lc)[0, 0])) < 1e-15
    other = Design.from_dict({**d.to_dict(), "Kdist": (d.Kdist + 40.0 * null).tolist()})
    w = _omega(d)
    np.testing.assert_allclose(
        sensitivity_response(other, w, True)[0], sensitivity_response(d, w, True)[0], rtol=1e-12
    )
