"""The estimator and feedback DAREs: residuals, stability, and agreement with independent solvers."""

from __future__ import annotations

import control
import numpy as np
import pytest

from dob_hil.design.riccati import (
    estimator_gain_from_Y,
    estimator_riccati_residual,
    feedback_gain_from_X,
    feedback_riccati_residual,
    solve_estimator_dare,
    solve_feedback_dare,
)
from dob_hil.errors import DesignError

from .helpers import random_stable_design_inputs

CASES = [(2, 1, 1), (3, 1, 2), (4, 2, 2), (5, 3, 2)]


def _iterate_estimator(Phi: np.ndarray, C: np.ndarray, Gam1: np.ndarray, D1: np.ndarray) -> np.ndarray:
    """The Riccati difference equation of the Kalman predictor, iterated from Y = 0 to convergence."""
    Y = np.zeros_like(Phi)
    for _ in range(20_000):
        S = D1 @ D1.T + C @ Y @ C.T
        Y_next = Phi @ Y @ Phi.T - Phi @ Y @ C.T @ np.linalg.solve(S, C @ Y @ Phi.T) + Gam1 @ Gam1.T
        if np.linalg.norm(Y_next - Y) <= 1e-14 * np.linalg.norm(Y_next):
            return Y_next
        Y = Y_next
    raise AssertionError("Riccati iteration did not converge")


def _iterate_feedback(Phi: np.ndarray, Gam: np.ndarray, R1: np.ndarray, R2: np.ndarray) -> np.ndarray:
    X = np.zeros_like(Phi)
    for _ in range(20_000):
        X_next = (
            Phi.T @ X @ Phi - Phi.T @ X @ Gam @ np.linalg.solve(R2 + Gam.T @ X @ Gam, Gam.T @ X @ Phi) + R1
        )
        if np.linalg.norm(X_next - X) <= 1e-14 * np.linalg.norm(X_next):
            return X_next
        X = X_next
    raise AssertionError("Riccati iteration did not converge")


@pytest.mark.parametrize(("n", "m", "p"), CASES)
def test_estimator_dare_residual_stability_and_independent_solutions(n: int, m: int, p: int) -> None:
    rng = np.random.default_rng(10 * n + p)
    Phi, _, C = random_stable_design_inputs(rng, n, m, p)
    Gam1 = rng.normal(size=(n, 2))
    D1 = rng.normal(size=(p, p)) + 2 * np.eye(p)
    sol = solve_estimator_dare(Phi, C, Gam1, D1)
    assert sol.relative_residual < 1e-10
    assert estimator_riccati_residual(sol.P, Phi, C, Gam1, D1) == sol.relative_residual
    assert np.all(np.linalg.eigvalsh(sol.P) > 0)
    assert max(sol.closed_loop_magnitudes) < 1.0
    np.testing.assert_allclose(
        sorted(sol.closed_loop_magnitudes),
        sorted(abs(np.linalg.eigvals(Phi - Phi @ sol.gain @ C))),
        rtol=1e-12,
    )
    # Independent: python-control's dare on the dual problem, and the Riccati difference equation.
    Y_ct, _, _ = control.dare(Phi.T, C.T, Gam1 @ Gam1.T, D1 @ D1.T)
    np.testing.assert_allclose(sol.P, Y_ct, rtol=1e-8, atol=1e-10 * np.linalg.norm(Y_ct))
    Y_it = _iterate_estimator(Phi, C, Gam1, D1)
    np.testing.assert_allclose(sol.P, Y_it, rtol=1e-7, atol=1e-9 * np.linalg.norm(Y_it))
    np.testing.assert_allclose(sol.gain, estimator_gain_from_Y(Y_it, C, D1), rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize(("n", "m", "p"), CASES)
def test_feedback_dare_residual_stability_and_independent_solutions(n: int, m: int, p: int) -> None:
    rng = np.random.default_rng(100 + 10 * n + m)
    Phi, Gam, C = random_stable_design_inputs(rng, n, m, p)
    q = 10.0 ** rng.uniform(-1, 3)
    R1 = q * C.T @ C
    R1 = 0.5 * (R1 + R1.T)  # BLAS may leave C.T @ C asymmetric in the last bit
    A = rng.normal(size=(m, m))
    R2 = A @ A.T + np.eye(m)
    sol = solve_feedback_dare(Phi, Gam, R1, R2)
    assert sol.relative_residual < 1e-10
    assert feedback_riccati_residual(sol.P, Phi, Gam, R1, R2) == sol.relative_residual
    assert max(sol.closed_loop_magnitudes) < 1.0
    X_ct, _, K_ct = control.dare(Phi, Gam, R1, R2)
    np.testing.assert_allclose(sol.P, X_ct, rtol=1e-8, atol=1e-10 * np.linalg.norm(X_ct))
    np.testing.assert_allclose(sol.gain, K_ct, rtol=1e-7, atol=1e-10)
    X_it = _iterate_feedback(Phi, Gam, R1, R2)
    np.testing.assert_allclose(sol.P, X_it, rtol=1e-7, atol=1e-9 * np.linalg.norm(X_it))
    np.testing.assert_allclose(sol.gain, feedback_gain_from_X(X_it, Phi, Gam, R2), rtol=1e-6, atol=1e-9)


def test_weights_that_are_not_positive_definite_are_refused() -> None:
    Phi, Gam, C = np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.0], [0.1]]), np.array([[1.0, 0.0]])
    with pytest.raises(DesignError, match=r"design\.feedback\.R2: must be positive definite"):
        solve_feedback_dare(Phi, Gam, C.T @ C, np.zeros((1, 1)))
    with pytest.raises(DesignError, match=r"design\.feedback\.R2: must be symmetric"):
        solve_feedback_dare(np.eye(2), np.eye(2), np.eye(2), np.array([[1.0, 0.5], [0.0, 1.0]]))
    with pytest.raises(DesignError, match=r"D1 D1'"):
        solve_estimator_dare(Phi, C, Gam, np.zeros((1, 1)))
    with pytest.raises(DesignError, match=r"Gam1: expected 2 rows"):
        solve_estimator_dare(Phi, C, np.ones((3, 1)), np.eye(1))


def test_no_stabilising_solution_is_a_design_error() -> None:
    """An unstable mode the input cannot reach: (Phi, Gam) is not stabilisable."""
    Phi = np.diag([1.2, 0.5])
    Gam = np.array([[0.0], [1.0]])
    with pytest.raises(DesignError, match="feedback DARE"):
        solve_feedback_dare(Phi, Gam, np.eye(2), np.eye(1))
