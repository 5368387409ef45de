"""Small linear-algebra helpers shared by the design modules: array types, eigenvalue magnitudes,
relative residuals and batched frequency responses of discrete-time state-space models."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

Matrix = npt.NDArray[np.float64]
CMatrix = npt.NDArray[np.complex128]
Vector = npt.NDArray[np.float64]


def eigenvalue_magnitudes(M: Matrix) -> list[float]:
    """All eigenvalue magnitudes of ``M``, sorted ascending (the paper's "rho-set")."""
    return sorted(float(v) for v in np.abs(np.linalg.eigvals(M)))


def spectral_radius(M: Matrix) -> float:
    """rho(M) = max |eig(M)|; 0 for an empty matrix."""
    if M.size == 0:
        return 0.0
    return float(np.max(np.abs(np.linalg.eigvals(M))))


def relative_residual(residual: Matrix, *scale_terms: Matrix) -> float:
    """||residual||_F / max(1e-300, sum of ||term||_F): a Riccati residual relative to its terms."""
    scale = sum(float(np.linalg.norm(t)) for t in scale_terms)
    return float(np.linalg.norm(residual)) / max(scale, 1e-300)


def unit_circle_points(omega_rad_s: npt.ArrayLike, period_s: float) -> CMatrix:
    """z = exp(j omega Ts) for each angular frequency (rad/s)."""
    w = np.asarray(omega_rad_s, dtype=np.float64).ravel()
    return np.asarray(np.exp(1j * w * period_s), dtype=np.complex128)


def frequency_response(A: Matrix, B: Matrix, C: Matrix, D: Matrix, z: CMatrix) -> CMatrix:
    """G(z) = C (zI - A)^-1 B + D at every point of ``z``; shape (len(z), outputs, inputs)."""
    n = A.shape[0]
    zs = np.asarray(z, dtype=np.complex128).ravel()
    if n == 0:
        return np.broadcast_to(D.astype(np.complex128), (zs.size, *D.shape)).copy()
    lhs = zs[:, None, None] * np.eye(n) - A[None, :, :]
    rhs = np.broadcast_to(B.astype(np.complex128), (zs.size, *B.shape))
    X = np.linalg.solve(lhs, rhs)
    out: CMatrix = (C.astype(np.complex128) @ X + D).astype(np.complex128)
    return out


def max_singular_value(G: CMatrix) -> Vector:
    """sigma_max of each (.., r, c) matrix of a frequency response; shape (len,)."""
    if G.shape[-1] == 1 or G.shape[-2] == 1:
        return np.asarray(np.sqrt(np.sum(np.abs(G) ** 2, axis=(-2, -1))), dtype=np.float64)
    return np.asarray(np.linalg.svd(G, compute_uv=False)[..., 0], dtype=np.float64)


def min_singular_value(G: CMatrix) -> Vector:
    """sigma_min of each (.., r, c) matrix of a frequency response; shape (len,)."""
    return np.asarray(np.linalg.svd(G, compute_uv=False)[..., -1], dtype=np.float64)


def frequency_grid_hz(period_ns: int, points: int = 1500, decades: float = 5.0) -> Vector:
    """Log-spaced frequencies (Hz) from ``decades`` below the Nyquist frequency up to Nyquist."""
    nyquist_hz = 0.5e9 / period_ns
    return np.asarray(np.logspace(np.log10(nyquist_hz) - decades, np.log10(nyquist_hz), points))
