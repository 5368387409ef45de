"""Designing the disturbance-observer gain Kdist, and the algebra that shows what it can do.

What the algebra shows. At run time ``u_dist = Kdist (x_bar - x_hat) = -Kdist Lc (y - C x_bar)``
(eq. 14): Kdist reaches the loop only through the m x p product ``Kdist Lc``, a static gain on the
estimator's innovation. Any two Kdist with the same Kdist Lc give the same controller.

The DOB is itself a feedback loop. With e = x - x_bar and an input disturbance w (through Gam_w),

    e(k+1) = (A0 - Gam Kdist Lc C) e(k) + Gam_w w(k),     A0 = Phi - Phi Lc C,
    -u_dist = Kdist Lc C e,

so the disturbance estimate is ``-u_dist = (I + G(z))^-1 Kdist Lc H_w(z) w`` with the DOB loop gain
``G(z) = Kdist Lc H(z)`` and ``H(z) = C (zI - A0)^-1 Gam`` (the innovation's response to an input at
the plant input, seen through the estimator). Without delay H_w = H and the estimate is
``Q(z) w = G (I + G)^-1 w``: the DOB's own complementary sensitivity, the disturbance-to-estimate
filter (:func:`disturbance_estimate_response`; Q(1) = 0.5055 for the paper's gains). It is *not* the
output loop's T = Lo (I + Lo)^-1, which the paper likens to a classical DOB's Q filter. Its stability
is exactly rho(A0 - Gam Kdist Lc C) < 1 (Theorem 1).

Design methods (``config.design.dob.method``; the gain direction is ``D = pinv(H(1))``, so that
``Kdist Lc = k D`` makes the DOB loop's DC gain ``G(1) = k I`` when H(1) has full row rank). What
each one optimises, and how it can disappoint:

* ``dc_loop_gain`` (default, gain k default 1): Kdist Lc = k D, i.e. it fixes the DOB loop's DC
  gain. It optimises nothing: without delay the estimate of a constant disturbance is
  Q(1) = k / (1 + k), so k = 1 estimates 50 % of it by construction (the paper's own
  Kdist = [18, 3.75] is this direction with k = 1.022: Q(1) = 0.5055).
* ``dc_estimate`` (gain f in (0, 1), default 0.8): the k whose DC disturbance estimate Q(1) reaches
  the fraction f (sigma_min(Q(1)) = f; exact also with an input delay, where Q(1) != k / (1 + k)).
* ``stable_fraction`` (gain f in (0, 1), default 0.25): k = f k_max, where k_max is the edge of the
  stable range (the smallest k > 0 with rho(A0 - k Gam D C) = 1). It keeps a stated distance from
  instability in gain only; near the edge the loop is poorly damped (f = 0.5 gives peak |S| 2.9 on the
  paper's plant), so the robustness checks of ``robustness`` apply to it like to every method.
* ``min_radius`` (gain f in (0, 1), default 0.5): k minimising rho(A0 - k Gam D C) over the stable
  gains that estimate at least the fraction f of a constant disturbance (sigma_min(Q(1)) >= f): the
  fastest disturbance estimate that still estimates something. Without that floor the minimum is at
  k = 0 whenever the DOB only slows the estimator (every Riccati-designed estimator tried: the DARE
  already places the estimator's poles), i.e. no DOB at all; when the minimum sits on the floor the
  design says so.
* ``optimize``: see :mod:`dob_hil.design.optimize` (best rejection over a band within robustness and
  noise bounds).

A designed gain that is identically zero is refused (DesignError); a DOB whose DC estimate is below
``MIN_DC_ESTIMATE`` is reported with a warning (``DobDesign.warnings``).

Kdist is then the minimum-norm solution ``Kdist = (k D) pinv(Lc)`` (needs rank(Lc) = p).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dob_hil.design.linalg import CMatrix, Matrix, Vector, frequency_response, spectral_radius
from dob_hil.design.theorem1 import estimator_matrix
from dob_hil.errors import ConfigError, DesignError

DOB_METHODS = ("dc_loop_gain", "dc_estimate", "stable_fraction", "min_radius", "optimize")
DEFAULT_DOB_METHOD = "dc_loop_gain"
DEFAULT_GAINS: dict[str, float] = {
    "dc_loop_gain": 1.0,
    "dc_estimate": 0.8,
    "stable_fraction": 0.25,
    "min_radius": 0.5,
}
# What each method chooses (printed by the report).
METHOD_AIMS: dict[str, str] = {
    "explicit": "Kdist given in the config",
    "dc_loop_gain": "fixes the DOB loop's DC gain k (estimates k / (1 + k) of a constant disturbance); "
    "optimises nothing",
    "dc_estimate": "estimates the fraction `gain` of a constant disturbance (sigma_min(Q(1)) = gain)",
    "stable_fraction": "k = gain x the edge of the stable range; a gain margin along the locus only",
    "min_radius": "fastest estimate (least spectral radius) among gains estimating >= `gain` of a constant "
    "disturbance",
    "optimize": "best worst-case rejection over [design.optimize] band_hz within its robustness and noise "
    "bounds",
}
# Methods whose gain is a fraction in (0, 1).
FRACTION_METHODS = ("dc_estimate", "stable_fraction", "min_radius")
# A DOB estimating less than this fraction of a constant disturbance (sigma_min(Q(1))) is reported.
MIN_DC_ESTIMATE = 0.2
# The stable-range search scans k over this many decades above and below the reference gain.
_SCAN_DECADES = (-4.0, 6.0)
_SCAN_POINTS = 600


@dataclass(frozen=True)
class DobDesign:
    """The DOB gain, how it was obtained, and where it sits on its locus.

    ``direction`` (m x p) and ``gain`` satisfy ``Kdist Lc = gain * direction``; ``direction_kind`` says
    whether the direction is ``pinv(H(1))`` (gain = DOB loop DC gain) or the given ``Kdist Lc`` itself
    (gain = 1 is the design). ``k_max`` is the edge of the stable range along the direction (None if
    none was found up to 1e6 times the reference gain, or the estimator alone is unstable);
    ``k_min_radius``/``min_radius`` the best radius over the scanned gains. ``warnings`` are the
    design's own complaints (a weak DOB); the robustness checks are in ``robustness``.
    """

    Kdist: Matrix
    Kdist_Lc: Matrix
    method: str
    direction: Matrix
    direction_kind: str
    gain: float
    k_max: float | None
    k_min_radius: float
    min_radius: float
    H1: Matrix
    dc_loop_gain: Matrix
    dc_estimate_gain: Matrix
    warnings: tuple[str, ...] = ()


def innovation_dc_gain(Phi: Matrix, Gam: Matrix, C: Matrix, Lc: Matrix) -> Matrix:
    """H(1) = C (I - A0)^-1 Gam with A0 = Phi - Phi Lc C (p x m). Needs A0 stable (no pole at 1)."""
    A0 = estimator_matrix(Phi, C, Lc)
    N = Phi.shape[0]
    return np.asarray(C @ np.linalg.solve(np.eye(N) - A0, Gam), dtype=np.float64)


def dc_estimate_gain(
    Phi: Matrix, Gam: Matrix, Gam_w: Matrix, C: Matrix, Lc: Matrix, *, Kdist: Matrix
) -> Matrix:
    """Q(1): steady-state gain from a constant input disturbance w to the estimate -u_dist (m x m)."""
    N = Phi.shape[0]
    F = Kdist @ Lc @ C
    Ae = estimator_matrix(Phi, C, Lc) - Gam @ F
    return np.asarray(F @ np.linalg.solve(np.eye(N) - Ae, Gam_w), dtype=np.float64)


def locus_radius(A0: Matrix, Gam: Matrix, C: Matrix, direction: Matrix, gains: Vector) -> Vector:
    """rho(A0 - k Gam direction C) for each k in ``gains``."""
    GMC = Gam @ direction @ C
    return np.array([spectral_radius(A0 - float(k) * GMC) for k in np.asarray(gains).ravel()])


def locus_magnitudes(A0: Matrix, Gam: Matrix, C: Matrix, direction: Matrix, gains: Vector) -> Matrix:
    """All eigenvalue magnitudes (sorted, one row per gain) of A0 - k Gam direction C."""
    GMC = Gam @ direction @ C
    return np.array(
        [np.sort(np.abs(np.linalg.eigvals(A0 - float(k) * GMC))) for k in np.asarray(gains).ravel()]
    )


def stable_edge(A0: Matrix, Gam: Matrix, C: Matrix, direction: Matrix, k_ref: float) -> float | None:
    """Smallest k > 0 with rho(A0 - k Gam direction C) = 1 (A0 must be stable), or None if the locus
    stays inside the unit circle over the scanned range (up to 1e6 k_ref)."""
    import scipy.optimize

    def f(k: float) -> float:
        return spectral_radius(A0 - k * (Gam @ direction @ C)) - 1.0

    if f(0.0) >= 0.0:
        raise DesignError(
            f"estimator: rho(Phi - Phi Lc C) = {f(0.0) + 1.0:.4g} >= 1; no stable DOB gain range "
            "starts at k = 0 (a DOB design method needs a stable estimator; give Kdist explicitly)"
        )
    grid = k_ref * np.logspace(_SCAN_DECADES[0], _SCAN_DECADES[1], _SCAN_POINTS)
    prev = 0.0
    for k in grid:
        if f(float(k)) >= 0.0:
            return float(scipy.optimize.brentq(f, prev, float(k), xtol=1e-12 * float(k), rtol=1e-12))
        prev = float(k)
    return None


def min_dc_estimate(Phi: Matrix, Gam: Matrix, Gam_w: Matrix, C: Matrix, Lc: Matrix, KdLc: Matrix) -> float:
    """sigma_min(Q(1)) for the DOB product ``Kdist Lc`` (the smallest fraction of a constant input
    disturbance, over its directions, that the DOB estimates)."""
    Kd = np.asarray(KdLc @ np.linalg.pinv(Lc), dtype=np.float64)
    Q1 = dc_estimate_gain(Phi, Gam, Gam_w, C, Lc, Kdist=Kd)
    return float(np.linalg.svd(Q1, compute_uv=False)[-1])


def gain_for_dc_estimate(
    Phi: Matrix,
    Gam: Matrix,
    Gam_w: Matrix,
    C: Matrix,
    Lc: Matrix,
    direction: Matrix,
    fraction: float,
    k_hi: float,
) -> float:
    """The smallest k in (0, k_hi] with sigma_min(Q(1)) = ``fraction`` along ``direction``."""
    import scipy.optimize

    def f(k: float) -> float:
        return min_dc_estimate(Phi, Gam, Gam_w, C, Lc, k * direction) - fraction

    grid = np.linspace(0.0, k_hi, 401)[1:]
    prev = 0.0
    for k in grid:
        if f(float(k)) >= 0.0:
            return float(scipy.optimize.brentq(f, prev, float(k), xtol=1e-12 * float(k), rtol=1e-12))
        prev = float(k)
    best = max(min_dc_estimate(Phi, Gam, Gam_w, C, Lc, float(k) * direction) for k in grid)
    raise DesignError(
        f"design.dob: no stable DOB gain estimates {fraction:.3g} of a constant disturbance "
        f"(at most {best:.3g} for 0 < k <= {k_hi:.4g}); lower design.dob.gain"
    )


def min_radius_gain(
    A0: Matrix, Gam: Matrix, C: Matrix, direction: Matrix, k_hi: float, *, k_lo: float = 0.0
) -> tuple[float, float]:
    """(k, rho) minimising rho(A0 - k Gam direction C) over k_lo <= k <= k_hi (grid, then Brent)."""
    import scipy.optimize

    grid = np.linspace(k_lo, k_hi, 801)
    rho = locus_radius(A0, Gam, C, direction, grid)
    i = int(np.argmin(rho))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    res = scipy.optimize.minimize_scalar(
        lambda k: spectral_radius(A0 - k * (Gam @ direction @ C)),
        bounds=(float(lo), float(hi)),
        method="bounded",
        options={"xatol": 1e-10 * max(k_hi, 1e-300)},
    )
    k_best, rho_best = float(res.x), float(res.fun)
    if rho[i] <= rho_best:
        k_best, rho_best = float(grid[i]), float(rho[i])
    return k_best, rho_best


def _kdist_from_product(KdLc: Matrix, Lc: Matrix) -> Matrix:
    p = Lc.shape[1]
    rank = int(np.linalg.matrix_rank(Lc))
    if rank < p:
        raise DesignError(
            f"design.dob: Lc has rank {rank} < p = {p}, so Kdist Lc cannot be chosen freely; "
            "give Kdist explicitly"
        )
    return np.asarray(KdLc @ np.linalg.pinv(Lc), dtype=np.float64)


def _direction_of(KdLc: Matrix, D: Matrix) -> tuple[Matrix, str, float]:
    """Express a given Kdist Lc along D = pinv(H(1)) when it is parallel to D, else along itself."""
    dd = float(np.sum(D * D))
    if dd > 0.0:
        k = float(np.sum(KdLc * D)) / dd
        if k > 0.0 and np.linalg.norm(KdLc - k * D) <= 1e-9 * max(float(np.linalg.norm(KdLc)), 1e-300):
            return D, "pinv(H(1))", k
    if float(np.linalg.norm(KdLc)) == 0.0:
        return D, "pinv(H(1))", 0.0
    return KdLc, "Kdist Lc", 1.0


def design_dob(
    Phi: Matrix,
    Gam: Matrix,
    Gam_w: Matrix,
    C: Matrix,
    Lc: Matrix,
    *,
    Kdist: Matrix | None,
    method: str | None,
    gain: float | None,
    explicit_label: str = "explicit",
    locus: bool = True,
) -> DobDesign:
    """Kdist given explicitly (``Kdist``, reported as ``explicit_label``) or designed by
    ``method``/``gain`` (see the module docstring).

    A design method requires a stable estimator (rho(Phi - Phi Lc C) < 1); an explicit Kdist does not
    (Theorem 1 needs only the DOB matrix stable). ``locus=False`` skips the stable-range and
    fastest-gain search for an explicit Kdist (k_max None, min radius NaN): what ``run`` needs, without
    scipy.optimize. Raises ConfigError for an unknown method or a gain out of range, DesignError when
    the method cannot be applied or designs Kdist = 0.
    """
    A0 = estimator_matrix(Phi, C, Lc)
    N = Phi.shape[0]
    a0_stable = spectral_radius(A0) < 1.0
    if not a0_stable and Kdist is None:
        raise DesignError(
            f"estimator: rho(Phi - Phi Lc C) = {spectral_radius(A0):.4g} >= 1; a DOB design method "
            "needs a stable estimator (give Kdist explicitly: Theorem 1 then needs only the DOB "
            "matrix stable)"
        )
    if abs(np.linalg.det(np.eye(N) - A0)) > 1e-300:
        H1 = innovation_dc_gain(Phi, Gam, C, Lc)
    else:
        H1 = np.zeros((C.shape[0], Gam.shape[1]))
    D = np.asarray(np.linalg.pinv(H1), dtype=np.float64)
    if Kdist is not None:
        KdLc = Kdist @ Lc
        direction, kind, k = _direction_of(KdLc, D)
        used_method = explicit_label
        Kd = Kdist
    else:
        used_method = method or DEFAULT_DOB_METHOD
        if used_method not in DOB_METHODS or used_method == "optimize":
            raise ConfigError(
                "design.dob.method", f"must be one of {', '.join(DOB_METHODS)}; got {used_method!r}"
            )
        if not float(np.linalg.norm(D)) > 0.0:
            raise DesignError(
                "design.dob: H(1) = C (I - Phi + Phi Lc C)^-1 Gam is zero; give Kdist explicitly"
            )
        direction, kind = D, "pinv(H(1))"
        k = DEFAULT_GAINS[used_method] if gain is None else gain
        if used_method in FRACTION_METHODS and not 0.0 < k < 1.0:
            raise ConfigError("design.dob.gain", f"{used_method} needs 0 < gain < 1, got {k:g}")
        Kd = np.zeros((Gam.shape[1], N))
    fraction = k
    k_ref = k if k > 0.0 and math.isfinite(k) and used_method not in FRACTION_METHODS else 1.0
    if not locus and Kdist is not None:
        k_max, k_hi = None, 1e3 * k_ref
        k_best, rho_best = math.nan, math.nan
    elif a0_stable:
        k_max = stable_edge(A0, Gam, C, direction, k_ref)
        k_hi = k_max if k_max is not None else 1e3 * k_ref
        k_best, rho_best = min_radius_gain(A0, Gam, C, direction, k_hi)
    else:
        k_max, k_hi = None, 1e3 * k_ref
        k_best, rho_best = k, spectral_radius(dob_matrix_of(A0, Gam, C, Kd @ Lc))
    notes: list[str] = []
    if used_method == "stable_fraction":
        if k_max is None:
            raise DesignError(
                "design.dob: the DOB locus stays stable for every scanned gain, so stable_fraction "
                "has no range; use dc_estimate or min_radius"
            )
        k = fraction * k_max
    elif used_method == "dc_estimate":
        k = gain_for_dc_estimate(Phi, Gam, Gam_w, C, Lc, direction, fraction, k_hi * (1 - 1e-9))
    elif used_method == "min_radius":
        k_floor = gain_for_dc_estimate(Phi, Gam, Gam_w, C, Lc, direction, fraction, k_hi * (1 - 1e-9))
        k_best, rho_best = min_radius_gain(A0, Gam, C, direction, k_hi, k_lo=k_floor)
        k = k_best
        if k <= k_floor * (1.0 + 1e-6):
            notes.append(
                f"design.dob: min_radius: the spectral radius only grows with the DOB gain beyond "
                f"the DC-estimate floor {fraction:g}; the design is the floor itself (k = {k:.4g}), "
                "so it is no faster than the estimator without the DOB"
            )
    if used_method in DOB_METHODS:
        Kd = _kdist_from_product(k * direction, Lc)
        if not np.any(Kd @ Lc):
            raise DesignError(
                f"design.dob: method {used_method} designed Kdist Lc = 0 (no DOB at all); "
                "choose another method or give Kdist"
            )
    KdLc = Kd @ Lc
    try:
        Q1 = dc_estimate_gain(Phi, Gam, Gam_w, C, Lc, Kdist=Kd)
    except np.linalg.LinAlgError:  # the DOB matrix has an eigenvalue at 1: Theorem 1 refuses it
        Q1 = np.full((Gam.shape[1], Gam_w.shape[1]), np.nan)
    q1 = float(np.linalg.svd(Q1, compute_uv=False)[-1]) if np.all(np.isfinite(Q1)) else math.nan
    if not np.any(KdLc):
        notes.append("design.dob: Kdist Lc = 0: the DOB does nothing (it estimates no disturbance)")
    elif q1 < MIN_DC_ESTIMATE:
        notes.append(
            f"design.dob: the DOB estimates only {100 * q1:.1f} % of a constant disturbance "
            f"(sigma_min(Q(1)) < {MIN_DC_ESTIMATE:g}): it attenuates slow disturbances by less than "
            f"{1 / (1 - MIN_DC_ESTIMATE):.2f}x"
        )
    return DobDesign(
        Kdist=np.asarray(Kd, dtype=np.float64),
        Kdist_Lc=np.asarray(KdLc, dtype=np.float64),
        method=used_method,
        direction=direction,
        direction_kind=kind,
        gain=float(k),
        k_max=k_max,
        k_min_radius=k_best,
        min_radius=rho_best,
        H1=H1,
        dc_loop_gain=np.asarray(KdLc @ H1, dtype=np.float64),
        dc_estimate_gain=Q1,
        warnings=tuple(notes),
    )


def dob_matrix_of(A0: Matrix, Gam: Matrix, C: Matrix, KdLc: Matrix) -> Matrix:
    """A0 - Gam (Kdist Lc) C: the DOB matrix from the estimator matrix and the DOB product."""
    return np.asarray(A0 - Gam @ KdLc @ C, dtype=np.float64)


def disturbance_estimate_response(
    Phi: Matrix, Gam: Matrix, Gam_w: Matrix, C: Matrix, Lc: Matrix, Kdist: Matrix, z: CMatrix
) -> CMatrix:
    """Q(z): the input disturbance w -> the DOB's estimate -u_dist (m x m per point of ``z``).

    Q(z) = Kdist Lc C (zI - (Phi - Phi Lc C - Gam Kdist Lc C))^-1 Gam_w: the estimation error obeys
    e' = A_dob e + Gam_w w and -u_dist = Kdist Lc C e, independently of Kc and the reference. This is
    the DOB's "Q filter" (Q(1) = ``dc_estimate_gain``); T is *not* (T is the output loop's
    complementary sensitivity)."""
    KdLcC = Kdist @ Lc @ C
    A = estimator_matrix(Phi, C, Lc) - Gam @ KdLcC
    m = Gam.shape[1]
    return frequency_response(A, Gam_w, KdLcC, np.zeros((m, Gam_w.shape[1])), z)
