"""The two discrete algebraic Riccati equations of the paper and their gains.

Estimator (eq. 6-7), H2 current estimator with process weight Gam1 (N x r) and sensor weight D1 (p x s):

    Y  = Phi Y Phi' - Phi Y C' (D1 D1' + C Y C')^-1 C Y Phi' + Gam1 Gam1'
    Lc = Y C' (C Y C' + D1 D1')^-1

Feedback (eq. 10-11), with R1 = q C'C for loop transfer recovery at the plant output:

    X  = Phi' X Phi - Phi' X Gam (R2 + Gam' X Gam)^-1 Gam' X Phi + R1
    Kc = (Gam' X Gam + R2)^-1 Gam' X Phi

Both are solved with ``scipy.linalg.solve_discrete_are`` (the estimator one in its dual form
``a = Phi', b = C'``). Each solver validates the weights, returns the solution with its relative
residual and the closed-loop eigenvalue magnitudes, and raises :class:`DesignError` when there is no
stabilising solution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dob_hil.design.linalg import Matrix, eigenvalue_magnitudes, relative_residual
from dob_hil.errors import DesignError


@dataclass(frozen=True)
class DareSolution:
    """A DARE solution ``P`` (Y or X), its ``gain`` (Lc or Kc), the relative residual of the equation
    (||residual||_F over the sum of the Frobenius norms of its terms) and the closed-loop eigenvalue
    magnitudes (of Phi - Phi Lc C, or of Phi - Gam Kc), sorted ascending."""

    P: Matrix
    gain: Matrix
    relative_residual: float
    closed_loop_magnitudes: list[float]


def _check_positive_definite(M: Matrix, what: str) -> None:
    if not np.allclose(M, M.T, rtol=1e-12, atol=1e-300):
        raise DesignError(f"{what}: must be symmetric")
    eig = np.linalg.eigvalsh(0.5 * (M + M.T))
    if eig.size and eig[0] <= 1e-12 * max(1.0, float(eig[-1])):
        raise DesignError(f"{what}: must be positive definite (smallest eigenvalue {eig[0]:.3g})")


def estimator_riccati_residual(Y: Matrix, Phi: Matrix, C: Matrix, Gam1: Matrix, D1: Matrix) -> float:
    """Relative residual of eq. 6 at ``Y``."""
    Rv = D1 @ D1.T
    S = Rv + C @ Y @ C.T
    t1 = Phi @ Y @ Phi.T
    t2 = Phi @ Y @ C.T @ np.linalg.solve(S, C @ Y @ Phi.T)
    t3 = Gam1 @ Gam1.T
    return relative_residual(t1 - t2 + t3 - Y, t1, t2, t3, Y)


def feedback_riccati_residual(X: Matrix, Phi: Matrix, Gam: Matrix, R1: Matrix, R2: Matrix) -> float:
    """Relative residual of eq. 10 at ``X``."""
    S = R2 + Gam.T @ X @ Gam
    t1 = Phi.T @ X @ Phi
    t2 = Phi.T @ X @ Gam @ np.linalg.solve(S, Gam.T @ X @ Phi)
    return relative_residual(t1 - t2 + R1 - X, t1, t2, R1, X)


def estimator_gain_from_Y(Y: Matrix, C: Matrix, D1: Matrix) -> Matrix:
    """Lc = Y C' (C Y C' + D1 D1')^-1 (eq. 7)."""
    S = C @ Y @ C.T + D1 @ D1.T
    return np.asarray(np.linalg.solve(S.T, (Y @ C.T).T).T, dtype=np.float64)


def feedback_gain_from_X(X: Matrix, Phi: Matrix, Gam: Matrix, R2: Matrix) -> Matrix:
    """Kc = (Gam' X Gam + R2)^-1 Gam' X Phi (eq. 11)."""
    return np.asarray(np.linalg.solve(Gam.T @ X @ Gam + R2, Gam.T @ X @ Phi), dtype=np.float64)


def solve_estimator_dare(Phi: Matrix, C: Matrix, Gam1: Matrix, D1: Matrix) -> DareSolution:
    """Solve eq. 6 for Y and return Lc of eq. 7. ``Gam1`` is N x r, ``D1`` is p x s with D1 D1' > 0."""
    import scipy.linalg

    N, p = Phi.shape[0], C.shape[0]
    if Gam1.shape[0] != N:
        raise DesignError(f"design.estimator.Gam1: expected {N} rows, got {Gam1.shape[0]}")
    if D1.shape[0] != p:
        raise DesignError(f"design.estimator.D1: expected {p} rows, got {D1.shape[0]}")
    _check_positive_definite(D1 @ D1.T, "design.estimator.D1 D1'")
    try:
        Y = scipy.linalg.solve_discrete_are(Phi.T, C.T, Gam1 @ Gam1.T, D1 @ D1.T)
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise DesignError(
            f"estimator DARE (eq. 6) has no stabilising solution: {exc} "
            "(is (Phi, C) detectable and (Phi, Gam1) free of uncontrollable unit-circle modes?)"
        ) from None
    Y = np.asarray(0.5 * (Y + Y.T), dtype=np.float64)
    Lc = estimator_gain_from_Y(Y, C, D1)
    return DareSolution(
        P=Y,
        gain=Lc,
        relative_residual=estimator_riccati_residual(Y, Phi, C, Gam1, D1),
        closed_loop_magnitudes=eigenvalue_magnitudes(Phi - Phi @ Lc @ C),
    )


def solve_feedback_dare(Phi: Matrix, Gam: Matrix, R1: Matrix, R2: Matrix) -> DareSolution:
    """Solve eq. 10 for X and return Kc of eq. 11. ``R1`` N x N >= 0, ``R2`` m x m > 0."""
    import scipy.linalg

    N, m = Phi.shape[0], Gam.shape[1]
    if R1.shape != (N, N):
        raise DesignError(f"design.feedback.R1: expected {N}x{N}, got {R1.shape[0]}x{R1.shape[1]}")
    if R2.shape != (m, m):
        raise DesignError(f"design.feedback.R2: expected {m}x{m}, got {R2.shape[0]}x{R2.shape[1]}")
    _check_positive_definite(R2, "design.feedback.R2")
    try:
        X = scipy.linalg.solve_discrete_are(Phi, Gam, R1, R2)
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise DesignError(
            f"feedback DARE (eq. 10) has no stabilising solution: {exc} "
            "(is (Phi, Gam) stabilisable and (Phi, C) free of unobservable unit-circle modes?)"
        ) from None
    X = np.asarray(0.5 * (X + X.T), dtype=np.float64)
    Kc = feedback_gain_from_X(X, Phi, Gam, R2)
    return DareSolution(
        P=X,
        gain=Kc,
        relative_residual=feedback_riccati_residual(X, Phi, Gam, R1, R2),
        closed_loop_magnitudes=eigenvalue_magnitudes(Phi - Gam @ Kc),
    )
