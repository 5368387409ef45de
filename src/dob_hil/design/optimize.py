"""The ``optimize`` DOB design: the best disturbance rejection over a band within robustness bounds.

Problem (``[design.optimize]``, see ``dob_hil.config.OptimizeConfig``)::

    minimise   max over the band of sigma_max(w -> y)          (worst rejection in band_hz)
    subject to closed loop stable with margin (Theorem 1 radius <= 0.999)
               peak |S| <= max_peak_S, peak |T| <= max_peak_T
               RMS noise-to-current <= max_noise_rms_A, peak <= max_noise_peak_A (if given)
               |GM| >= min_gain_margin_dB, PM >= min_phase_margin_deg (loop at a time, plant input)
               balanced disk margins >= min_disk_gain_margin_dB / min_disk_phase_margin_deg (if given;
               loop at a time, and for several inputs also the multiloop margin at the plant input)
               delay margin >= min_delay_margin_samples

over ``Kdist Lc`` (tune = "kdist"; Kdist = (Kdist Lc) pinv(Lc)) or directly over Lc, Kc and Kdist Lc
(tune = "all"). Bounds left out of the config default to the starting design's own value (peak |T|,
RMS noise) so that the result is never worse than the start in them. All figures come from
:func:`dob_hil.design.robustness.evaluate`. Solver: scipy.optimize SLSQP from the starting design,
then COBYLA from SLSQP's point; the best point that meets every bound wins (the start when nothing
better is feasible: the result says so). scipy.optimize is imported here only (not on ``run``'s path
unless the config asks for this method).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from dob_hil.design.dob import dc_estimate_gain
from dob_hil.design.linalg import Matrix
from dob_hil.design.robustness import FloatArray, Merit, analysis_grid_rad_s, evaluate
from dob_hil.errors import ConfigError, DesignError

if TYPE_CHECKING:
    from dob_hil.config import Config, OptimizeConfig

RADIUS_LIMIT = 0.999
BAND_POINTS = 7


@dataclass(frozen=True)
class Bounds:
    max_peak_S: float
    max_peak_T: float
    max_noise_rms_A: float
    max_noise_peak_A: float | None
    min_gain_margin_dB: float
    min_phase_margin_deg: float
    min_disk_gain_margin_dB: float | None
    min_disk_phase_margin_deg: float | None
    min_delay_margin_samples: float

    def slack(self, m: Merit, period_s: float) -> FloatArray:
        """One entry per bound, >= 0 when it holds (relative, so that entries are comparable)."""
        g = [
            (RADIUS_LIMIT - m.closed_loop_radius) * 100.0,
            (self.max_peak_S - m.peak_S) / self.max_peak_S,
            (self.max_peak_T - m.peak_T) / self.max_peak_T,
            (self.max_noise_rms_A - float(np.max(m.noise_rms_A))) / self.max_noise_rms_A,
            (abs(m.gain_margin_db) - self.min_gain_margin_dB) / max(self.min_gain_margin_dB, 1.0),
            (m.phase_margin_deg - self.min_phase_margin_deg) / max(self.min_phase_margin_deg, 1.0),
            (m.delay_margin_s / period_s - self.min_delay_margin_samples)
            / max(self.min_delay_margin_samples, 1.0),
        ]
        if self.max_noise_peak_A is not None:
            g.append((self.max_noise_peak_A - m.noise_peak_A) / self.max_noise_peak_A)
        if self.min_disk_gain_margin_dB is not None:
            g.append((m.disk_gain_margin_db - self.min_disk_gain_margin_dB) / self.min_disk_gain_margin_dB)
        if self.min_disk_phase_margin_deg is not None:
            g.append(
                (m.disk_phase_margin_deg - self.min_disk_phase_margin_deg) / self.min_disk_phase_margin_deg
            )
        return np.array([min(v, 10.0) if math.isfinite(v) else (10.0 if v > 0 else -10.0) for v in g])

    def as_dict(self) -> dict[str, float | None]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class OptimizeResult:
    Lc: Matrix
    Kc: Matrix
    Kdist: Matrix
    tune: str
    band_hz: tuple[float, float]
    bounds: Bounds
    start: Merit
    merit: Merit
    improved: bool
    solver: str
    start_Lc: Matrix
    start_Kc: Matrix

    @property
    def rejection_gain(self) -> float:
        """How many times better the worst in-band rejection is than the start's."""
        return self.start.worst_rejection / self.merit.worst_rejection

    @property
    def summary(self) -> str:
        lo, hi = self.band_hz
        return (
            f"tune {self.tune}, band {lo:g}-{hi:g} Hz, worst rejection {self.merit.worst_rejection:.4g} "
            f"({self.rejection_gain:.2f}x the start's) by {self.solver}"
        )


def _band(cfg: OptimizeConfig, config: Config) -> tuple[float, float]:
    if cfg.band_hz is not None:
        return cfg.band_hz
    freqs = [d.frequency_hz for d in config.sim.disturbances if d.kind == "sine" and d.frequency_hz > 0]
    if not freqs:
        raise ConfigError(
            "design.optimize.band_hz",
            "missing (and no sine disturbance in [sim] to take the band from): give [lo, hi] in Hz",
        )
    return (min(freqs), max(freqs))


def band_frequencies(band: tuple[float, float]) -> FloatArray:
    lo, hi = band
    return np.asarray(np.geomspace(lo, hi, BAND_POINTS) if hi > lo else np.array([lo]), dtype=np.float64)


@dataclass(frozen=True)
class Problem:
    """The parameterisation: x (scaled) -> (Lc, Kc, Kdist); and the merit of a point."""

    unpack: Callable[[FloatArray], tuple[Matrix, Matrix, Matrix]]
    merit: Callable[[Matrix, Matrix, Matrix], Merit]
    x0: FloatArray


def _problem(
    Phi: Matrix, Gam: Matrix, Gam_w: Matrix, C: Matrix, *, Lc: Matrix, Kc: Matrix, KdLc0: Matrix,
    tune: str, period_s: float, band: FloatArray, count: float, multiloop: bool = False,
) -> Problem:  # fmt: skip
    w = analysis_grid_rad_s(period_s, 400)

    def merit(L: Matrix, K: Matrix, Kd: Matrix) -> Merit:
        return evaluate(
            Phi, Gam, Gam_w, C, Lc=L, Kc=K, Kdist=Kd, period_s=period_s, omega_rad_s=w, band_hz=band,
            count=count, multiloop=multiloop,
        )  # fmt: skip

    def kdist(KdLc: Matrix, L: Matrix) -> Matrix:
        return np.asarray(KdLc @ np.linalg.pinv(L), dtype=np.float64)

    if tune == "kdist":
        scale = np.where(KdLc0 != 0.0, np.abs(KdLc0), 1.0).ravel()

        def unpack_k(x: FloatArray) -> tuple[Matrix, Matrix, Matrix]:
            return Lc, Kc, kdist((x * scale).reshape(KdLc0.shape), Lc)

        return Problem(unpack_k, merit, KdLc0.ravel() / scale)
    parts = (Lc, Kc, KdLc0)
    flat = np.concatenate([p.ravel() for p in parts])
    scale = np.where(flat != 0.0, np.abs(flat), 1.0)
    sizes = [p.size for p in parts]

    def unpack_all(x: FloatArray) -> tuple[Matrix, Matrix, Matrix]:
        v = x * scale
        L = v[: sizes[0]].reshape(Lc.shape)
        K = v[sizes[0] : sizes[0] + sizes[1]].reshape(Kc.shape)
        KdLc = v[sizes[0] + sizes[1] :].reshape(KdLc0.shape)
        return L, K, kdist(KdLc, L)

    return Problem(unpack_all, merit, flat / scale)


def _starting_product(
    Phi: Matrix, Gam: Matrix, Gam_w: Matrix, C: Matrix, Lc: Matrix, Kdist: Matrix | None
) -> Matrix:
    """Kdist Lc to start from: the config's explicit Kdist, else a DOB loop DC gain of one."""
    if Kdist is not None and np.any(Kdist @ Lc):
        return np.asarray(Kdist @ Lc, dtype=np.float64)
    from dob_hil.design.dob import innovation_dc_gain

    H1 = innovation_dc_gain(Phi, Gam, C, Lc)
    return np.asarray(np.linalg.pinv(H1), dtype=np.float64)


def solve(
    problem: Problem, bounds: Bounds, period_s: float, *, start_merit: Merit, maxiter: int = 200
) -> tuple[FloatArray, Merit, str, bool]:
    """Run SLSQP then COBYLA; return (x, merit, solver, improved) of the best feasible point."""
    import scipy.optimize

    cache: dict[bytes, Merit | None] = {}

    def merit_of(x: FloatArray) -> Merit | None:
        key = np.asarray(x, dtype=np.float64).tobytes()
        if key not in cache:
            try:
                m = problem.merit(*problem.unpack(x))
                cache[key] = m if all(math.isfinite(v) for v in (m.worst_rejection, m.peak_S)) else None
            except (np.linalg.LinAlgError, ValueError):
                cache[key] = None
        return cache[key]

    def objective(x: FloatArray) -> float:
        m = merit_of(x)
        if m is None or m.closed_loop_radius >= 1.0:
            return 50.0
        return float(math.log(m.worst_rejection / start_merit.worst_rejection))

    n_slack = bounds.slack(start_merit, period_s).size

    def constraints(x: FloatArray) -> FloatArray:
        m = merit_of(x)
        if m is None:
            return np.full(n_slack, -10.0)
        return bounds.slack(m, period_s)

    best_x, best_m, solver, improved = problem.x0, start_merit, "none (start kept)", False
    best_feasible = bool(np.min(bounds.slack(start_merit, period_s)) >= -1e-9)

    def consider(x: FloatArray, name: str) -> None:
        nonlocal best_x, best_m, solver, improved, best_feasible
        m = merit_of(x)
        if m is None or np.min(bounds.slack(m, period_s)) < -1e-9:
            return
        if not best_feasible or m.worst_rejection < best_m.worst_rejection * (1 - 1e-9):
            best_x, best_m, solver, improved, best_feasible = np.asarray(x), m, name, True, True

    cons = [{"type": "ineq", "fun": constraints}]
    res = scipy.optimize.minimize(
        objective, problem.x0, method="SLSQP", constraints=cons, options={"maxiter": maxiter, "ftol": 1e-9}
    )
    consider(res.x, "SLSQP")
    res2 = scipy.optimize.minimize(
        objective,
        best_x,
        method="COBYLA",
        constraints=cons,
        options={"maxiter": 10 * maxiter, "rhobeg": 0.05},
    )
    consider(res2.x, "SLSQP + COBYLA" if improved else "COBYLA")
    return best_x, best_m, solver, improved


def _bounds(cfg: OptimizeConfig, start: Merit) -> Bounds:
    return Bounds(
        max_peak_S=cfg.max_peak_S,
        max_peak_T=cfg.max_peak_T if cfg.max_peak_T is not None else start.peak_T,
        max_noise_rms_A=(
            cfg.max_noise_rms_A if cfg.max_noise_rms_A is not None else float(np.max(start.noise_rms_A))
        ),
        max_noise_peak_A=cfg.max_noise_peak_A,
        min_gain_margin_dB=cfg.min_gain_margin_dB,
        min_phase_margin_deg=cfg.min_phase_margin_deg,
        min_disk_gain_margin_dB=cfg.min_disk_gain_margin_dB,
        min_disk_phase_margin_deg=cfg.min_disk_phase_margin_deg,
        min_delay_margin_samples=cfg.min_delay_margin_samples,
    )


def optimize_design(
    config: Config, Phi: Matrix, Gam: Matrix, Gam_w: Matrix, C: Matrix, *, Lc: Matrix, Kc: Matrix,
    bounds: Bounds | None = None,
) -> OptimizeResult:  # fmt: skip
    """Optimise from the config's own design (Lc, Kc, and its explicit Kdist if any) per
    ``config.design.optimize``. ``bounds`` overrides the configured bounds (trade-off curves).
    Raises DesignError when even the start does not meet the bounds and nothing feasible is found."""
    cfg = config.design.optimize
    band = _band(cfg, config)
    period_s = config.plant.period_ns * 1e-9
    count = 1.0 / config.drive.encoder_counts_per_unit
    KdLc0 = _starting_product(Phi, Gam, Gam_w, C, Lc, config.design.dob.Kdist)
    # several inputs and a disk bound: bound the multiloop disk margin too (what the design warns on)
    disk = cfg.min_disk_gain_margin_dB is not None or cfg.min_disk_phase_margin_deg is not None
    problem = _problem(
        Phi, Gam, Gam_w, C, Lc=Lc, Kc=Kc, KdLc0=KdLc0, tune=cfg.tune, period_s=period_s,
        band=band_frequencies(band), count=count, multiloop=disk and Gam.shape[1] > 1,
    )  # fmt: skip
    start = problem.merit(*problem.unpack(problem.x0))
    b = bounds if bounds is not None else _bounds(cfg, start)
    x, merit, solver, improved = solve(problem, b, period_s, start_merit=start)
    if not improved and np.min(b.slack(start, period_s)) < -1e-9:
        raise DesignError(
            "design.optimize: no design meets the bounds (the start violates "
            + ", ".join(_violated(b, start, period_s))
            + "); relax [design.optimize]"
        )
    L, K, Kd = problem.unpack(x)
    if not np.any(Kd @ L):
        raise DesignError("design.optimize: the optimum has Kdist Lc = 0 (no DOB helps within the bounds)")
    # Q(1) must be finite: the DOB matrix is stable at a feasible point.
    dc_estimate_gain(Phi, Gam, Gam_w, C, L, Kdist=Kd)
    return OptimizeResult(L, K, Kd, cfg.tune, band, b, start, merit, improved, solver, Lc, Kc)


_NAMES = (
    "closed-loop radius", "peak |S|", "peak |T|", "RMS noise-to-current", "gain margin", "phase margin",
    "delay margin",
)  # fmt: skip


def _violated(b: Bounds, m: Merit, period_s: float) -> list[str]:
    names = list(_NAMES)
    if b.max_noise_peak_A is not None:
        names.append("peak noise-to-current")
    if b.min_disk_gain_margin_dB is not None:
        names.append("disk gain margin")
    if b.min_disk_phase_margin_deg is not None:
        names.append("disk phase margin")
    return [n for n, s in zip(names, b.slack(m, period_s), strict=True) if s < -1e-9]


@dataclass(frozen=True)
class TradeoffPoint:
    max_noise_rms_A: float
    noise_rms_A: float
    worst_rejection: float
    peak_S: float
    peak_T: float


def tradeoff_curve(
    config: Config, result: OptimizeResult, Phi: Matrix, Gam: Matrix, Gam_w: Matrix, C: Matrix,
    factors: tuple[float, ...] = (0.5, 0.75, 1.0, 1.5, 2.0, 3.0),
) -> list[TradeoffPoint]:  # fmt: skip
    """Rejection against RMS noise-to-current: the optimisation repeated with the noise bound scaled
    by each factor (other bounds unchanged), each started from the config's design."""
    out = []
    for f in factors:
        b = Bounds(**{**result.bounds.__dict__, "max_noise_rms_A": f * result.bounds.max_noise_rms_A})
        try:
            r = optimize_design(config, Phi, Gam, Gam_w, C, Lc=result.start_Lc, Kc=result.start_Kc, bounds=b)
        except DesignError:
            continue
        m = r.merit
        out.append(
            TradeoffPoint(
                b.max_noise_rms_A, float(np.max(m.noise_rms_A)), m.worst_rejection, m.peak_S, m.peak_T
            )
        )
    return out
