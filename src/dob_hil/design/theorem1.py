"""Theorem 1: the closed loop's eigenvalues are those of the feedback and of the DOB-estimator error.

With e = x - x_bar (plant state minus predicted state), no reference and no disturbance, the run-time
controller (``dob_hil.control.step``) gives

    e(k+1) = (Phi - Phi Lc C - Gam Kdist Lc C) e(k)
    x(k+1) = (Phi - Gam Kc) x(k) + Gam (Kc - Kc Lc C - Kdist Lc C) e(k)

a block-triangular system, so the closed loop's eigenvalues are exactly the union of those of the two
diagonal blocks (Theorem 1), and it is stable exactly when both are. With the DOB off (Kdist = 0)
the second block is the estimator matrix Phi - Phi Lc C. So the gate is: feedback stable, and the
DOB matrix (DOB on) or the estimator matrix (DOB off) stable; an unstable estimator alone is not
refused when the loop with the DOB is stable (that design then must not run with the DOB off).
"""

from __future__ import annotations

from dob_hil.design.linalg import Matrix, eigenvalue_magnitudes

# Matrix expressions as printed in reports and errors.
EXPRESSIONS: dict[str, str] = {
    "estimator": "Phi - Phi Lc C",
    "feedback": "Phi - Gam Kc",
    "dob": "Phi - Phi Lc C - Gam Kdist Lc C",
}


def estimator_matrix(Phi: Matrix, C: Matrix, Lc: Matrix) -> Matrix:
    """Phi - Phi Lc C: the current estimator's error dynamics without the DOB."""
    return Phi - Phi @ Lc @ C


def feedback_matrix(Phi: Matrix, Gam: Matrix, Kc: Matrix) -> Matrix:
    """Phi - Gam Kc: the state-feedback dynamics."""
    return Phi - Gam @ Kc


def dob_matrix(Phi: Matrix, Gam: Matrix, C: Matrix, Lc: Matrix, Kdist: Matrix) -> Matrix:
    """Phi - Phi Lc C - Gam Kdist Lc C: the estimator error dynamics with the DOB."""
    return Phi - Phi @ Lc @ C - Gam @ Kdist @ Lc @ C


def spectral_radii(
    Phi: Matrix, Gam: Matrix, C: Matrix, *, Lc: Matrix, Kc: Matrix, Kdist: Matrix
) -> dict[str, list[float]]:
    """All eigenvalue magnitudes (sorted ascending) of the three Theorem-1 matrices."""
    return {
        "estimator": eigenvalue_magnitudes(estimator_matrix(Phi, C, Lc)),
        "feedback": eigenvalue_magnitudes(feedback_matrix(Phi, Gam, Kc)),
        "dob": eigenvalue_magnitudes(dob_matrix(Phi, Gam, C, Lc, Kdist)),
    }


def unstable_parts(radii: dict[str, list[float]], dob_enabled: bool) -> list[str]:
    """Messages for every matrix whose eigenvalues are closed-loop eigenvalues (Theorem 1) with rho >= 1:
    the feedback matrix, and the dob matrix (DOB on) or the estimator matrix (DOB off)."""
    required = ["feedback", "dob" if dob_enabled else "estimator"]
    out = []
    for key in required:
        mags = radii[key]
        rho = max(mags) if mags else 0.0
        if not rho < 1.0:
            out.append(f"{key}: rho({EXPRESSIONS[key]}) = {rho:.4g} >= 1")
    return out
