"""Everything ``dob-hil design`` reports about a design, computed once: loop responses with and
without the DOB, margins, peak sensitivities, disturbance rejection, the DOB gain locus and the LTR
table. :meth:`DesignAnalysis.to_dict` is the JSON report (numbers only, no frequency arrays).

Margins are loop-at-a-time: for each channel of the loop broken at the plant *input* (Li = K P) and at
the plant *output* (Lo = P K), the scalar loop of that channel with every other loop closed
(for a SISO plant both are the same scalar loop K(z) P(z), negative feedback). Disk margins are the
balanced (skew 0) ones of MATLAB's ``diskmargin``, loop at a time; the delay margin, noise to current,
the disturbance-to-estimate filter Q(z) and the pole flags are defined in ``robustness`` and ``dob``.

Multiloop disk margins (``multiloop``): every channel of the breaking point perturbed at once by its
own balanced disk factor, alpha = 1 / max_w mu(F - I/2) with F = Si (plant input) or S (plant
output) and a diagonal complex uncertainty, as MATLAB's ``diskmargin(L)`` for a MIMO L. For a
single-input, single-output loop it equals the loop-at-a-time disk margin. Per input: the delay
margin (a transport delay in that input alone) and the peak noise to current of that input (row i of
K S, 2-norm: the worst direction of one count of encoder noise).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from dob_hil.config import Config
from dob_hil.design.build import DesignResult
from dob_hil.design.dob import METHOD_AIMS, disturbance_estimate_response, locus_magnitudes
from dob_hil.design.linalg import CMatrix, Matrix, frequency_grid_hz, max_singular_value, unit_circle_points
from dob_hil.design.loops import LoopResponse, design_loop_response, loop_at_a_time
from dob_hil.design.ltr import DEFAULT_LTR_Q_VALUES, LtrReport, error_definition, ltr_report
from dob_hil.design.margins import Margins, loop_margins
from dob_hil.design.multiloop import MultiloopDiskMargin, multiloop_disk_margin
from dob_hil.design.robustness import (
    DiskMargin,
    PoleFlag,
    classical_margins,
    disk_margin,
    noise_rms,
    pole_flags,
)
from dob_hil.design.theorem1 import EXPRESSIONS, dob_matrix, estimator_matrix, feedback_matrix

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Peak:
    value: float
    frequency_hz: float

    def as_dict(self) -> dict[str, float]:
        return {
            "value": self.value,
            "dB": 20.0 * math.log10(max(self.value, 1e-300)),
            "at_Hz": self.frequency_hz,
        }


@dataclass(frozen=True)
class LoopSummary:
    """Margins and peaks of one configuration (DOB on or off)."""

    response: LoopResponse
    margins_input: tuple[Margins, ...]
    margins_output: tuple[Margins, ...]
    peak_S: Peak
    peak_T: Peak
    peak_Si: Peak
    peak_disturbance: Peak
    low_frequency_disturbance_gain: float
    disturbance_at: tuple[tuple[float, float], ...]  # (frequency Hz, ||y/w|| for the configured input)
    disturbance_at_per_output: tuple[tuple[int, tuple[float, ...]], ...]  # (input index, |y_j / w|)
    noise_rms_A: tuple[float, ...]  # per input, one count RMS of white encoder noise
    noise_peak_A: Peak  # max over frequency of sigma_max(K S) * one count
    noise_to_current: FloatArray  # sigma_max(K S) * one count on the grid [A per count]
    disk_input: tuple[DiskMargin, ...]
    disk_output: tuple[DiskMargin, ...]
    delay_margin_s: float
    multiloop_input: MultiloopDiskMargin
    multiloop_output: MultiloopDiskMargin
    delay_margins_s: tuple[float, ...]  # per input (loop at a time)
    noise_peak_per_input_A: tuple[Peak, ...]  # max over frequency of ||row i of K S||_2 * one count
    noise_to_current_per_input: FloatArray  # ||row i of K S||_2 * one count, shape (grid, inputs) [A]


@dataclass(frozen=True)
class DesignAnalysis:
    result: DesignResult
    frequency_hz: FloatArray
    dob_on: LoopSummary
    dob_off: LoopSummary
    ltr: LtrReport
    locus_gain: FloatArray
    locus_magnitudes: Matrix
    dob_enabled: bool
    Q: CMatrix  # disturbance-to-estimate filter Q(z) on the grid (m x m)
    pole_flags: tuple[PoleFlag, ...]
    count: float  # one encoder count in output units

    def to_dict(self) -> dict[str, Any]:
        return report_dict(self)


def _peak(values: FloatArray, w: FloatArray, fn: Any) -> Peak:
    """Largest value on the grid, refined by a bounded search between its neighbours."""
    import scipy.optimize

    i = int(np.argmax(values))
    lo, hi = w[max(i - 1, 0)], w[min(i + 1, w.size - 1)]
    best, at = float(values[i]), float(w[i])
    if hi > lo:
        res = scipy.optimize.minimize_scalar(
            lambda x: -float(fn(np.array([x]))[0]), bounds=(float(lo), float(hi)), method="bounded"
        )
        if -float(res.fun) > best:
            best, at = -float(res.fun), float(res.x)
    return Peak(best, at / (2.0 * math.pi))


def _noise_rms(design: Any, Kdist: Matrix, count: float) -> FloatArray:
    return noise_rms(design.Phi, design.Gam, design.C, Lc=design.Lc, Kc=design.Kc, Kdist=Kdist, count=count)


def _summary(result: DesignResult, config: Config, w: FloatArray, dob_enabled: bool) -> LoopSummary:
    design = result.design

    def resp(x: FloatArray) -> LoopResponse:
        return design_loop_response(design, x, dob_enabled)

    r = resp(w)

    def loop_fn(kind: str, ch: int) -> Any:
        return lambda x: loop_at_a_time(resp(x).Si if kind == "input" else resp(x).S, ch)

    m_in = tuple(loop_margins(loop_fn("input", i), w) for i in range(design.n_inputs))
    m_out = tuple(loop_margins(loop_fn("output", i), w) for i in range(design.n_outputs))

    def sig(attr: str) -> Any:
        return lambda x: max_singular_value(getattr(resp(x), attr))

    count = 1.0 / config.drive.encoder_counts_per_unit
    KS = r.K @ r.S
    ks = max_singular_value(KS) * count
    rows = np.sqrt(np.sum(np.abs(KS) ** 2, axis=2)) * count  # (frequency, input)
    noise_rows = tuple(
        Peak(float(np.max(rows[:, i])), float(w[int(np.argmax(rows[:, i]))]) / (2.0 * math.pi))
        for i in range(design.n_inputs)
    )
    m_, p_ = design.n_inputs, design.n_outputs
    dms = [classical_margins(1.0 / r.Si[:, i, i] - 1.0, w)[2] for i in range(m_)]
    Kd = design.Kdist if dob_enabled else np.zeros_like(design.Kdist)
    dist_at: list[tuple[float, float]] = []
    dist_rows: list[tuple[int, tuple[float, ...]]] = []
    for dcfg in config.sim.disturbances:
        if dcfg.kind == "sine" and dcfg.frequency_hz > 0.0:
            x = np.array([2.0 * math.pi * dcfg.frequency_hz])
            col = resp(x).disturbance[0, :, dcfg.input_index]
            dist_at.append((dcfg.frequency_hz, float(np.linalg.norm(col))))
            dist_rows.append((dcfg.input_index, tuple(float(v) for v in np.abs(col))))
    return LoopSummary(
        response=r,
        margins_input=m_in,
        margins_output=m_out,
        peak_S=_peak(max_singular_value(r.S), w, sig("S")),
        peak_T=_peak(max_singular_value(r.T), w, sig("T")),
        peak_Si=_peak(max_singular_value(r.Si), w, sig("Si")),
        peak_disturbance=_peak(max_singular_value(r.disturbance), w, sig("disturbance")),
        low_frequency_disturbance_gain=float(max_singular_value(r.disturbance)[0]),
        disturbance_at=tuple(dist_at),
        disturbance_at_per_output=tuple(dist_rows),
        noise_rms_A=tuple(
            float(v)
            for v in noise_rms(
                design.Phi, design.Gam, design.C, Lc=design.Lc, Kc=design.Kc, Kdist=Kd, count=count
            )
        ),
        noise_peak_A=Peak(float(np.max(ks)), float(w[int(np.argmax(ks))]) / (2.0 * math.pi)),
        noise_to_current=np.asarray(ks, dtype=np.float64),
        disk_input=tuple(disk_margin(r.Si[:, i, i], w) for i in range(m_)),
        disk_output=tuple(disk_margin(r.S[:, i, i], w) for i in range(p_)),
        delay_margin_s=min(dms),
        multiloop_input=multiloop_disk_margin(r.Si, w, where="plant input", response=lambda x: resp(x).Si),
        multiloop_output=multiloop_disk_margin(r.S, w, where="plant output", response=lambda x: resp(x).S),
        delay_margins_s=tuple(dms),
        noise_peak_per_input_A=noise_rows,
        noise_to_current_per_input=np.asarray(rows, dtype=np.float64),
    )


def analyze(result: DesignResult, config: Config, points: int = 1500) -> DesignAnalysis:
    """Analyse a design (see the module docstring) on ``points`` log-spaced frequencies up to Nyquist."""
    design = result.design
    f = frequency_grid_hz(design.period_ns, points)
    w = 2.0 * math.pi * f
    dob = result.dob
    k_hi = 1.5 * dob.k_max if dob.k_max is not None else max(4.0 * dob.gain, 2.0 * dob.k_min_radius, 1.0)
    gains = np.unique(np.concatenate([np.linspace(0.0, k_hi, 400), [dob.gain, dob.k_min_radius]]))
    mags = locus_magnitudes(
        estimator_matrix(design.Phi, design.C, design.Lc), design.Gam, design.C, dob.direction, gains
    )
    q_values = config.design.feedback.ltr_q_values or DEFAULT_LTR_Q_VALUES
    Q = disturbance_estimate_response(
        design.Phi,
        design.Gam,
        design.Gam_w,
        design.C,
        design.Lc,
        design.Kdist,
        unit_circle_points(w, design.period_s),
    )
    flags = pole_flags(
        {
            EXPRESSIONS["feedback"]: feedback_matrix(design.Phi, design.Gam, design.Kc),
            EXPRESSIONS["dob"]: dob_matrix(design.Phi, design.Gam, design.C, design.Lc, design.Kdist),
            EXPRESSIONS["estimator"]: estimator_matrix(design.Phi, design.C, design.Lc),
        }
    )
    ltr = ltr_report(
        design.Phi,
        design.Gam,
        design.C,
        design.Lc,
        Kc_design=design.Kc,
        R2=result.R2,
        q_values=q_values,
        period_s=design.period_s,
        omega_rad_s=w,
        band_hz=config.design.feedback.ltr_band_hz,
    )
    return DesignAnalysis(
        result=result,
        frequency_hz=f,
        dob_on=_summary(result, config, w, True),
        dob_off=_summary(result, config, w, False),
        ltr=ltr,
        locus_gain=gains,
        locus_magnitudes=mags,
        dob_enabled=result.dob_enabled,
        Q=Q,
        pole_flags=tuple(flags),
        count=1.0 / config.drive.encoder_counts_per_unit,
    )


def _complex_list(M: Matrix) -> list[list[float]]:
    ev = np.linalg.eigvals(M)
    ev = ev[np.lexsort((ev.imag, np.abs(ev)))]
    return [[float(e.real), float(e.imag)] for e in ev]


def _finite_rows(M: Matrix) -> list[list[float | None]]:
    """A matrix as JSON rows, a non-finite entry (Q(1) of a DOB matrix with a pole at 1) as null."""
    return [[float(v) if math.isfinite(v) else None for v in row] for row in np.asarray(M).tolist()]


def _finite(v: float) -> float | None:
    return v if math.isfinite(v) else None


def _loop_dict(s: LoopSummary, period_s: float) -> dict[str, Any]:
    return {
        "margins_plant_input": [m.as_dict() for m in s.margins_input],
        "margins_plant_output": [m.as_dict() for m in s.margins_output],
        "peak_sensitivity": s.peak_S.as_dict(),
        "peak_complementary_sensitivity": s.peak_T.as_dict(),
        "peak_input_sensitivity": s.peak_Si.as_dict(),
        "disk_margins_plant_input": [d.as_dict() for d in s.disk_input],
        "disk_margins_plant_output": [d.as_dict() for d in s.disk_output],
        "multiloop_disk_margin_plant_input": s.multiloop_input.as_dict(),
        "multiloop_disk_margin_plant_output": s.multiloop_output.as_dict(),
        "delay_margin": {"s": _finite(s.delay_margin_s), "samples": _finite(s.delay_margin_s / period_s)},
        "delay_margin_per_input": [
            {"s": _finite(v), "samples": _finite(v / period_s)} for v in s.delay_margins_s
        ],
        "noise_to_current": {
            "rms_A_per_count_rms": list(s.noise_rms_A),
            "peak_A_per_count": s.noise_peak_A.value,
            "peak_at_Hz": s.noise_peak_A.frequency_hz,
            "peak_A_per_count_per_input": [p.value for p in s.noise_peak_per_input_A],
            "peak_at_Hz_per_input": [p.frequency_hz for p in s.noise_peak_per_input_A],
        },
        "disturbance_to_output": {
            "peak": s.peak_disturbance.as_dict(),
            "lowest_grid_frequency_gain": s.low_frequency_disturbance_gain,
            "at_configured_disturbances": [
                {"frequency_Hz": fr, "gain": g, "input_index": i, "gain_per_output": list(per_output)}
                for (fr, g), (i, per_output) in zip(
                    s.disturbance_at, s.disturbance_at_per_output, strict=True
                )
            ],
        },
    }


def report_dict(a: DesignAnalysis) -> dict[str, Any]:
    """The JSON report of ``dob-hil design``."""
    res, d = a.result, a.result.design
    dob = res.dob
    Kd_off = np.zeros_like(d.Kdist)

    def dare(sol: Any) -> dict[str, Any] | None:
        if sol is None:
            return None
        return {"solution": sol.P.tolist(), "relative_residual": sol.relative_residual}

    return {
        "name": d.name,
        "period_ns": d.period_ns,
        "nyquist_Hz": 0.5e9 / d.period_ns,
        "n_plant_states": d.n_plant_states,
        "input_delay_samples": d.input_delay_samples,
        "state_names": list(d.state_names),
        "input_names": list(d.input_names),
        "output_names": list(d.output_names),
        "A": d.A.tolist(),
        "B": d.B.tolist(),
        "C_cont": d.C_cont.tolist(),
        "Phi": d.Phi.tolist(),
        "Gam": d.Gam.tolist(),
        "Gam_w": d.Gam_w.tolist(),
        "C": d.C.tolist(),
        "Lc": d.Lc.tolist(),
        "Kc": d.Kc.tolist(),
        "Kdist": d.Kdist.tolist(),
        "Kdist_Lc": d.Kdist_Lc.tolist(),
        "gain_sources": dict(d.gain_sources),
        "dob_enabled": a.dob_enabled,
        "spectral_radii": {k: list(v) for k, v in d.spectral_radii.items()},
        "spectral_radii_dob_off": {
            "dob": sorted(
                float(x) for x in np.abs(np.linalg.eigvals(dob_matrix(d.Phi, d.Gam, d.C, d.Lc, Kd_off)))
            )
        },
        "eigenvalues": {
            "estimator": _complex_list(estimator_matrix(d.Phi, d.C, d.Lc)),
            "feedback": _complex_list(feedback_matrix(d.Phi, d.Gam, d.Kc)),
            "dob": _complex_list(dob_matrix(d.Phi, d.Gam, d.C, d.Lc, d.Kdist)),
        },
        "matrices": dict(EXPRESSIONS),
        "riccati": {"estimator": dare(res.estimator_dare), "feedback": dare(res.feedback_dare)},
        "dob": {
            "method": dob.method,
            "method_aim": METHOD_AIMS.get(dob.method, ""),
            "direction": dob.direction.tolist(),
            "direction_kind": dob.direction_kind,
            "gain": dob.gain,
            "stable_gain_limit": dob.k_max,
            "min_radius_gain": dob.k_min_radius,
            "min_radius": dob.min_radius,
            "H1": dob.H1.tolist(),
            "dc_loop_gain": dob.dc_loop_gain.tolist(),
            "dc_disturbance_estimate_gain": _finite_rows(dob.dc_estimate_gain),
        },
        "loop_dob_on": _loop_dict(a.dob_on, d.period_s),
        "loop_dob_off": _loop_dict(a.dob_off, d.period_s),
        "disturbance_estimate_filter": {
            "definition": "Q(z): input disturbance w -> DOB estimate -u_dist (not T)",
            "Q1": _finite_rows(dob.dc_estimate_gain),
            "peak": float(np.max(max_singular_value(a.Q))),
            "bandwidth_Hz": _bandwidth(a),
        },
        "pole_flags": [p.as_dict() for p in a.pole_flags],
        "warnings": list(res.warnings),
        "optimize": _optimize_dict(res),
        "ltr": {
            "target": "Gtl = C (zI - Phi)^-1 Phi Lc (eq. 8), loop broken at the plant output, DOB off",
            "R2": a.ltr.R2.tolist(),
            "band_Hz": list(a.ltr.band_hz),
            "error": error_definition(d.n_outputs),
            "recovered_at_q": a.ltr.recovered_at_q,
            "obstructions": list(a.ltr.obstructions),
            "notes": list(a.ltr.notes),
            "rows": [r.as_dict() for r in a.ltr.rows],
        },
    }


def _bandwidth(a: DesignAnalysis) -> float | None:
    """Lowest frequency where sigma_max(Q) drops below Q(1)'s sigma_max / sqrt(2)."""
    q = max_singular_value(a.Q)
    below = np.nonzero(q < q[0] / math.sqrt(2.0))[0]
    return float(a.frequency_hz[below[0]]) if below.size else None


def _optimize_dict(res: DesignResult) -> dict[str, Any] | None:
    o = res.optimized
    if o is None:
        return None

    def merit(m: Any) -> dict[str, Any]:
        return {
            "rejection_in_band": m.rejection.tolist(),
            "worst_rejection": m.worst_rejection,
            "peak_S": m.peak_S,
            "peak_T": m.peak_T,
            "noise_rms_A": m.noise_rms_A.tolist(),
            "noise_peak_A": m.noise_peak_A,
            "gain_margin_dB": _finite(m.gain_margin_db),
            "phase_margin_deg": _finite(m.phase_margin_deg),
            "disk_gain_margin_dB": _finite(m.disk_gain_margin_db),
            "disk_phase_margin_deg": m.disk_phase_margin_deg,
            "delay_margin_s": _finite(m.delay_margin_s),
            "multiloop_disk_margin_plant_input": (
                None if m.multiloop_input is None else m.multiloop_input.as_dict()
            ),
        }

    return {
        "tune": o.tune,
        "band_Hz": list(o.band_hz),
        "band_frequencies_Hz": o.merit.band_hz.tolist(),
        "bounds": o.bounds.as_dict(),
        "solver": o.solver,
        "improved": o.improved,
        "rejection_gain": o.rejection_gain,
        "start": merit(o.start),
        "result": merit(o.merit),
    }
