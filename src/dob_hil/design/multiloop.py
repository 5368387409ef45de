"""Multiloop (simultaneous) balanced disk margins of a MIMO loop, as MATLAB's ``diskmargin(L)``.

Break the loop at m channels (the plant input: the loop Li = K P of ``loops``, negative feedback,
with the run-time controller K -- current estimator, state feedback and the DOB's u_dist, u = -K y;
or the plant output: Lo = P K) and let every channel i be multiplied at the same time by its own,
independent balanced (skew 0) disk factor

    f_i = (1 + delta_i / 2) / (1 - delta_i / 2),   delta_i complex, |delta_i| < alpha.

With F = (I + L)^-1 the sensitivity at the breaking point, the closed loop stays stable for every
such perturbation iff alpha * mu_Delta(F(e^{jw}) - I/2) <= 1 at every frequency, where mu_Delta is the
structured singular value for a diagonal complex Delta = diag(delta_1..delta_m), and
F - I/2 = (S - T)/2 is the balanced sensitivity. Hence the multiloop disk margin

    alpha_max = 1 / max_w mu_Delta(F - I/2).

Its disk gain margin is +/- 20 log10((1 + alpha/2) / (1 - alpha/2)) dB (every channel's gain may
change by up to that factor at once), its disk phase margin +/- 2 atan(alpha/2). With an input delay
the break is at the command, before the delay line; a diagonal perturbation commutes with the
per-channel delay, so the margin is the same as right at the plant.

mu is bounded from both sides at each frequency:

* upper bound (what the margin uses, so the margin is guaranteed): the D-scaling bound
  min over positive diagonal D of sigma_max(D M D^-1). In log coordinates D = diag(e^x) this is a
  convex function of x (Sezginer and Overton 1990), so a local minimiser is global. Started from an
  Osborne balancing (numpy, vectorised over the grid) of |M|, the minimum is found by scipy.optimize
  (``minimize_scalar`` bounded for m = 2, Nelder-Mead over x_2..x_m for m > 2; on this non-smooth
  function Nelder-Mead may stop short of the minimum, and the value is then still an upper bound,
  only less tight: the lower bound below shows the gap). Only frequencies
  whose Osborne-balanced bound could still exceed the worst refined one are refined (any D gives an
  upper bound, so the skipped ones cannot hold the maximum).
* lower bound: mu(M) = max over diagonal unitary U of rho(M U) (Doyle 1982); any U gives a lower
  bound, rho(M) (U = I) the crudest. It is searched over the phases (scipy.optimize) at the worst
  frequency, which bounds alpha_max from above. For m <= 3 (diagonal complex blocks) mu equals the
  upper bound, so the two agree up to the search tolerance.

For m = 1 everything reduces to the loop-at-a-time margin (mu = |s - 1/2|).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from dob_hil.design.linalg import CMatrix, max_singular_value

FloatArray = npt.NDArray[np.float64]
ResponseFn = Callable[[FloatArray], CMatrix]

OSBORNE_SWEEPS = 12
LOG_SCALE_SPAN = 30.0  # search |x_i - x0_i| <= 30 (D entries within e^+-30 of the Osborne start)
METHOD = (
    "mu upper bound min_D sigma_max(D M D^-1): Osborne balancing (numpy) refined by scipy.optimize "
    "(minimize_scalar / Nelder-Mead, convex in log D); lower bound max_U rho(M U) by scipy.optimize"
)


def balanced_disk_gain_phase(alpha: float) -> tuple[float, float]:
    """(gain margin dB, phase margin deg) of a balanced (skew 0) disk of size alpha: the gain may
    change by a factor in [(1 - a/2)/(1 + a/2), (1 + a/2)/(1 - a/2)] (inf dB for a >= 2), the phase by
    +/- 2 atan(a/2)."""
    gm = math.inf if alpha >= 2.0 else 20.0 * math.log10((1.0 + alpha / 2.0) / (1.0 - alpha / 2.0))
    return gm, math.degrees(2.0 * math.atan(alpha / 2.0))


def balanced_sensitivity(F: CMatrix) -> CMatrix:
    """F - I/2 = (S - T)/2 for a sensitivity F = (I + L)^-1 (shape (k, m, m))."""
    m = F.shape[-1]
    return np.asarray(F - 0.5 * np.eye(m), dtype=np.complex128)


def osborne_scaling(M: CMatrix, sweeps: int = OSBORNE_SWEEPS) -> FloatArray:
    """Log scalings x (shape (k, m), x[:, 0] = 0) from Osborne's iteration on |M|: each sweep scales
    row and column i of D |M| D^-1 to equal off-diagonal 2-norms (vectorised over the first axis).
    A row or column without off-diagonal entries keeps its scale."""
    A = np.abs(np.asarray(M))
    k, m, _ = A.shape
    x = np.zeros((k, m))
    off = ~np.eye(m, dtype=bool)
    for _ in range(sweeps):
        for i in range(m):
            d = np.exp(x)
            B = A * d[:, :, None] / d[:, None, :]
            row = np.sqrt(np.sum((B[:, i, :] * off[i]) ** 2, axis=1))
            col = np.sqrt(np.sum((B[:, :, i] * off[:, i]) ** 2, axis=1))
            ok = (row > 0.0) & (col > 0.0)
            x[ok, i] += 0.5 * np.log(col[ok] / row[ok])
    x -= x[:, :1]
    return np.clip(x, -LOG_SCALE_SPAN, LOG_SCALE_SPAN)


def scaled_norm(M: CMatrix, x: FloatArray) -> FloatArray:
    """sigma_max(D M D^-1) with D = diag(exp(x)), batched over the first axis."""
    d = np.exp(np.asarray(x, dtype=np.float64))
    return max_singular_value(np.asarray(M) * d[:, :, None] / d[:, None, :])


def _refine_one(M: CMatrix, x0: FloatArray) -> tuple[float, FloatArray]:
    """min over x (x[0] = 0) of sigma_max(D M D^-1), from x0; scipy.optimize."""
    import scipy.optimize

    m = M.shape[0]

    def f(y: FloatArray) -> float:
        x = np.concatenate([[0.0], np.atleast_1d(y)])
        return float(scaled_norm(M[None], x[None])[0])

    start = float(f(x0[1:]))
    best_x, best = np.array(x0, dtype=np.float64), start
    if m == 2:
        c = float(x0[1])
        res = scipy.optimize.minimize_scalar(
            f, bounds=(c - LOG_SCALE_SPAN, c + LOG_SCALE_SPAN), method="bounded", options={"xatol": 1e-10}
        )
        cand = np.array([0.0, float(res.x)])
        val = float(res.fun)
    else:
        res = scipy.optimize.minimize(
            f, x0[1:], method="Nelder-Mead",
            options={"xatol": 1e-10, "fatol": 1e-13 * max(start, 1e-300),
                     "maxiter": 4000 * m, "maxfev": 8000 * m},
        )  # fmt: skip
        cand = np.concatenate([[0.0], res.x])
        val = float(res.fun)
    if val < best:
        best_x, best = cand, val
    return best, best_x


def mu_upper_bound(M: CMatrix) -> tuple[FloatArray, FloatArray]:
    """(bound, x): the D-scaling upper bound of mu for a diagonal complex Delta at every matrix of
    ``M`` (shape (k, m, m)) and its log scalings (D = diag(exp(x)), x[:, 0] = 0)."""
    M = np.asarray(M, dtype=np.complex128)
    k, m, _ = M.shape
    if m == 1:
        return np.abs(M[:, 0, 0]).astype(np.float64), np.zeros((k, 1))
    x0 = osborne_scaling(M)
    out = np.empty(k)
    xs = np.empty((k, m))
    for i in range(k):
        out[i], xs[i] = _refine_one(M[i], x0[i])
    return out, xs


def mu_lower_bound(M: CMatrix, starts: int = 16) -> FloatArray:
    """max over diagonal unitary U of rho(M U), a lower bound of mu for a diagonal complex Delta, at
    every matrix of ``M`` (shape (k, m, m)): a phase grid (m = 2) or ``starts`` random phase vectors,
    refined by scipy.optimize. Never below rho(M)."""
    import scipy.optimize

    M = np.asarray(M, dtype=np.complex128)
    k, m, _ = M.shape
    if m == 1:
        return np.abs(M[:, 0, 0]).astype(np.float64)
    rng = np.random.default_rng(0)
    out = np.empty(k)
    for i in range(k):
        Mi = M[i]

        def neg_rho(th: FloatArray, Mi: CMatrix = Mi) -> float:
            u = np.exp(1j * np.concatenate([[0.0], np.atleast_1d(th)]))
            return -float(np.max(np.abs(np.linalg.eigvals(Mi * u[None, :]))))

        if m == 2:
            grid = np.linspace(-math.pi, math.pi, 73)
            vals = [neg_rho(np.array([t])) for t in grid]
            j = int(np.argmin(vals))
            res = scipy.optimize.minimize_scalar(
                lambda t: neg_rho(np.array([t])),
                bounds=(grid[max(j - 1, 0)], grid[min(j + 1, grid.size - 1)]),
                method="bounded",
                options={"xatol": 1e-10},
            )
            best = max(-float(vals[j]), -float(res.fun))
        else:
            tries = [np.zeros(m - 1)] + [rng.uniform(-math.pi, math.pi, m - 1) for _ in range(starts - 1)]
            best = 0.0
            for th0 in tries:
                res = scipy.optimize.minimize(neg_rho, th0, method="Nelder-Mead",
                                              options={"xatol": 1e-9, "fatol": 1e-12})  # fmt: skip
                best = max(best, -float(res.fun))
        out[i] = max(best, -neg_rho(np.zeros(m - 1)))
    return out


@dataclass(frozen=True)
class MultiloopDiskMargin:
    """The balanced multiloop disk margin of one loop-breaking point (module docstring)."""

    where: str  # "plant input" or "plant output"
    channels: int
    alpha: float  # guaranteed: 1 / max_w mu upper bound
    alpha_upper: float  # 1 / mu lower bound at the worst frequency: alpha_max <= this
    gain_margin_db: float  # +/- (balanced disk), inf for alpha >= 2
    phase_margin_deg: float  # +/-
    at_hz: float
    mu_upper: float
    mu_lower: float
    scaling: tuple[float, ...]  # D at the worst frequency (first entry 1)
    refined_points: int  # grid frequencies refined by scipy.optimize (the others were pruned)

    def as_dict(self) -> dict[str, object]:
        return {
            "where": self.where,
            "uncertainty": f"diag(delta_1..delta_{self.channels}), complex, independent per channel",
            "alpha": self.alpha,
            "alpha_upper_bound": self.alpha_upper,
            "gain_margin_dB": _finite(self.gain_margin_db),
            "gain_margin_low_dB": _finite(-self.gain_margin_db),
            "gain_margin_high_dB": _finite(self.gain_margin_db),
            "phase_margin_deg": self.phase_margin_deg,
            "at_Hz": self.at_hz,
            "mu_upper_bound": self.mu_upper,
            "mu_lower_bound": self.mu_lower,
            "D_scaling": list(self.scaling),
            "method": METHOD,
        }


def _finite(v: float) -> float | None:
    return v if math.isfinite(v) else None


def _worst_on_grid(M: CMatrix) -> tuple[int, float, FloatArray, int]:
    """(index, mu upper bound, x, refined count) of the grid point with the largest optimised upper
    bound; grid points whose Osborne bound is below the best refined value are skipped."""
    m = M.shape[-1]
    if m == 1:
        mags = np.abs(M[:, 0, 0])
        i = int(np.argmax(mags))
        return i, float(mags[i]), np.zeros(1), 0
    x0 = osborne_scaling(M)
    cheap = scaled_norm(M, x0)
    order = np.argsort(-cheap)
    best_i, best, best_x, refined = int(order[0]), -1.0, x0[order[0]], 0
    for i in order:
        if cheap[i] <= best:
            break
        val, x = _refine_one(M[i], x0[i])
        refined += 1
        if val > best:
            best_i, best, best_x = int(i), val, x
    return best_i, best, best_x, refined


def multiloop_disk_margin(
    F: CMatrix, omega_rad_s: FloatArray, *, where: str = "plant input", response: ResponseFn | None = None
) -> MultiloopDiskMargin:
    """The balanced multiloop disk margin from the sensitivity F = (I + L)^-1 on the ascending grid
    ``omega_rad_s`` (shape (k, m, m)). ``response(w) -> F`` (optional) refines the worst frequency
    between its grid neighbours (scipy.optimize.minimize_scalar)."""
    w = np.asarray(omega_rad_s, dtype=np.float64)
    M = balanced_sensitivity(np.asarray(F, dtype=np.complex128))
    m = M.shape[-1]
    i, mu_up, x, refined = _worst_on_grid(M)
    at = float(w[i])
    Mw = M[i]
    if response is not None and w.size > 1:
        import scipy.optimize

        def neg_mu(wx: float) -> float:
            Mx = balanced_sensitivity(response(np.array([wx])))
            if m == 1:
                return -float(abs(Mx[0, 0, 0]))
            return -_refine_one(Mx[0], x)[0]

        lo, hi = float(w[max(i - 1, 0)]), float(w[min(i + 1, w.size - 1)])
        if hi > lo:
            res = scipy.optimize.minimize_scalar(neg_mu, bounds=(lo, hi), method="bounded")
            if -float(res.fun) > mu_up:
                at = float(res.x)
                Mw = balanced_sensitivity(response(np.array([at])))[0]
                mu_up, x = _refine_one(Mw, x) if m > 1 else (float(abs(Mw[0, 0])), np.zeros(1))
    mu_lo = float(mu_lower_bound(Mw[None])[0])
    mu_lo = min(mu_lo, mu_up)  # equal in exact arithmetic for m <= 3; never report lower > upper
    alpha = 1.0 / mu_up if mu_up > 0.0 else math.inf
    gm, pm = balanced_disk_gain_phase(alpha)
    return MultiloopDiskMargin(
        where=where,
        channels=m,
        alpha=alpha,
        alpha_upper=1.0 / mu_lo if mu_lo > 0.0 else math.inf,
        gain_margin_db=gm,
        phase_margin_deg=pm,
        at_hz=at / (2.0 * math.pi),
        mu_upper=mu_up,
        mu_lower=mu_lo,
        scaling=tuple(float(v) for v in np.exp(x)),
        refined_points=refined,
    )
