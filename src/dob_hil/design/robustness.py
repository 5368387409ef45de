"""Figures of merit a control engineer chooses by, for any (Lc, Kc, Kdist) of the run-time controller.

* Disturbance rejection: sigma_max of w -> y (``S Pw``, see ``loops``) at given frequencies.
* Peak |S| and |T| at the plant output (sigma_max).
* Noise to current: encoder noise n added to y (one count = 1 / ``encoder_counts_per_unit`` output
  units) reaches the command as ``u = -K S n``. ``noise_peak_A`` = max_w sigma_max(K S) * count (one
  count alternating each sample near Nyquist); ``noise_rms_A`` = the H2 norm * count per input: the
  RMS current for white encoder noise of one count RMS on every output, from the closed loop's
  discrete Lyapunov equation.
* Balanced disk margins (as MATLAB's ``diskmargin`` with skew sigma = 0), loop at a time: for the
  scalar loop l of one channel with all others closed, s = 1 / (1 + l) is that channel's diagonal
  entry of S (or Si), and the largest disk of simultaneous gain/phase changes
  f = (1 + delta/2) / (1 - delta/2), |delta| < alpha, that keeps the loop stable has
  alpha = 1 / max_w |s - 1/2| = 2 / max_w |s - t| (t = 1 - s). The disk gain margin is
  (1 + alpha/2) / (1 - alpha/2) (infinite for alpha >= 2) and the disk phase margin 2 atan(alpha/2).
  The multiloop margin (all channels perturbed at once, a mu problem) is in ``multiloop``.
* Delay margin: the extra loop delay that destabilises, min over the gain crossovers w_c of
  (angle(-l(w_c)) mod 2 pi) / w_c (loop at a time at the plant input, where a transport delay acts),
  in seconds and samples.
* Pole flags: closed-loop eigenvalues (Theorem 1: those of Phi - Gam Kc and of the DOB matrix) that
  are negative real (the mode alternates sign each sample: command chatter) or lightly damped
  (equivalent damping ratio of s = ln(z) / Ts below ``LIGHT_DAMPING``).

:func:`design_warnings` checks a design against ``ROBUSTNESS_BOUNDS`` (and the configured disk-margin
bounds) and says what is violated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from dob_hil.design.linalg import CMatrix, Matrix, max_singular_value
from dob_hil.design.loops import LoopResponse, controller_state_space, loop_response
from dob_hil.design.multiloop import MultiloopDiskMargin, balanced_disk_gain_phase, multiloop_disk_margin
from dob_hil.design.theorem1 import dob_matrix, feedback_matrix

if TYPE_CHECKING:
    from dob_hil.design.artifact import Design

FloatArray = npt.NDArray[np.float64]

# The robustness bounds every design is checked against (a design violating one gets a warning).
ROBUSTNESS_BOUNDS: dict[str, float] = {
    "max_peak_S": 2.0,  # 6 dB
    "min_gain_margin_dB": 6.0,
    "min_phase_margin_deg": 30.0,
    "min_delay_margin_samples": 1.0,
    # the balanced multiloop disk margin at the plant input (all inputs perturbed at once), checked for
    # multi-input plants; ``design.optimize.min_disk_gain_margin_dB`` / ``min_disk_phase_margin_deg``
    # replace these and then apply to single-input plants too (where it is the loop's disk margin)
    "min_disk_gain_margin_dB": 6.0,
    "min_disk_phase_margin_deg": 30.0,
}
LIGHT_DAMPING = 0.1
# a multiloop disk margin within this fraction of its bound meets it (the optimiser bounds it on a
# coarser grid than the report's refined one)
DISK_BOUND_TOLERANCE = 1e-3
NEGATIVE_REAL_MIN_MAGNITUDE = 0.3


class DesignWarning(UserWarning):
    """A design that runs but violates a robustness bound or has a weak DOB."""


@dataclass(frozen=True)
class DiskMargin:
    alpha: float
    gain_margin_db: float  # + and - this many dB (balanced disk)
    phase_margin_deg: float
    at_hz: float

    def as_dict(self) -> dict[str, float | None]:
        """JSON form; an infinite gain margin (alpha >= 2) is null. The balanced disk's gain range
        is [-gain_margin_dB, +gain_margin_dB] (``gain_margin_low_dB``, ``gain_margin_high_dB``)."""
        gm = self.gain_margin_db if math.isfinite(self.gain_margin_db) else None
        return {
            "alpha": self.alpha,
            "gain_margin_dB": gm,
            "gain_margin_low_dB": None if gm is None else -gm,
            "gain_margin_high_dB": gm,
            "phase_margin_deg": self.phase_margin_deg,
            "at_Hz": self.at_hz,
        }


def disk_margin(s: npt.NDArray[np.complex128], omega_rad_s: FloatArray) -> DiskMargin:
    """Balanced (skew 0) disk margin from a scalar sensitivity s = 1 / (1 + l) on a frequency grid."""
    dist = np.abs(np.asarray(s) - 0.5)
    i = int(np.argmax(dist))
    alpha = 1.0 / float(dist[i])
    gm, pm = balanced_disk_gain_phase(alpha)
    return DiskMargin(alpha, gm, pm, float(omega_rad_s[i]) / (2.0 * math.pi))


def classical_margins(loop: npt.NDArray[np.complex128], w: FloatArray) -> tuple[float, float, float]:
    """(gain margin dB, phase margin deg, delay margin s) of a scalar loop on a grid, crossings found
    by linear interpolation: the smallest |GM| over phase crossovers, the smallest PM and the smallest
    (PM mod 360 deg) / w_c over gain crossovers (inf where there is no crossover)."""
    mag = np.abs(loop) - 1.0
    gm = math.inf
    im = loop.imag
    idx = np.nonzero((im[:-1] * im[1:] <= 0.0) & (loop.real[:-1] < 0.0))[0]
    for i in idx:
        a = im[i] / (im[i] - im[i + 1]) if im[i] != im[i + 1] else 0.0
        re = loop.real[i] + a * (loop.real[i + 1] - loop.real[i])
        if re < 0.0:
            g = -20.0 * math.log10(-re)
            gm = g if abs(g) < abs(gm) else gm
    if loop[-1].real < 0.0 and abs(loop[-1].imag) <= 1e-9 * abs(loop[-1]):
        g = -20.0 * math.log10(-loop[-1].real)
        gm = g if abs(g) < abs(gm) else gm
    pm, dm = math.inf, math.inf
    for i in np.nonzero(mag[:-1] * mag[1:] <= 0.0)[0]:
        a = mag[i] / (mag[i] - mag[i + 1]) if mag[i] != mag[i + 1] else 0.0
        wc = w[i] + a * (w[i + 1] - w[i])
        ph = np.angle(-(loop[i] + a * (loop[i + 1] - loop[i])))
        pm = min(pm, math.degrees(ph), key=abs)
        dm = min(dm, float(ph) % (2.0 * math.pi) / wc)  # the lag e^{-j w tau} that turns l into -1
    return gm, pm, dm


@dataclass(frozen=True)
class PoleFlag:
    matrix: str
    real: float
    imag: float
    magnitude: float
    damping: float
    kind: str  # "negative real" or "lightly damped"

    def as_dict(self) -> dict[str, object]:
        return {
            "matrix": self.matrix,
            "eigenvalue": [self.real, self.imag],
            "magnitude": self.magnitude,
            "damping_ratio": self.damping,
            "kind": self.kind,
        }


def damping_ratio(z: complex) -> float:
    """Damping ratio of s = ln(z) / Ts (independent of Ts); 1 for z = 0, a real positive z < 1."""
    if z == 0:
        return 1.0
    s = complex(np.log(complex(z)))
    return float(-s.real / abs(s)) if abs(s) > 0 else 0.0


def pole_flags(matrices: dict[str, Matrix]) -> list[PoleFlag]:
    """Eigenvalues worth a flag: negative real (|z| >= 0.3) or lightly damped (zeta < LIGHT_DAMPING)."""
    out = []
    for name, M in matrices.items():
        for ev in np.linalg.eigvals(M):
            z = complex(ev)
            if z.imag < -1e-12:
                continue  # one of a conjugate pair
            zeta = damping_ratio(z)
            if abs(z.imag) <= 1e-9 * max(1.0, abs(z)) and z.real <= -NEGATIVE_REAL_MIN_MAGNITUDE:
                out.append(PoleFlag(name, z.real, 0.0, abs(z), zeta, "negative real"))
            elif zeta < LIGHT_DAMPING and abs(z) > 1e-6:
                out.append(PoleFlag(name, z.real, z.imag, abs(z), zeta, "lightly damped"))
    return out


def closed_loop_noise_system(
    Phi: Matrix, Gam: Matrix, C: Matrix, *, Lc: Matrix, Kc: Matrix, Kdist: Matrix
) -> tuple[Matrix, Matrix, Matrix, Matrix]:
    """(A, B, Cu, Du): the closed loop from measurement noise n (y = C x + n) to the command u."""
    k = controller_state_space(Phi, Gam, C, Lc=Lc, Kc=Kc, Kdist=Kdist)
    A = np.block([[Phi - Gam @ k.Dk @ C, -Gam @ k.Ck], [k.Bk @ C, k.Ak]])
    B = np.vstack([-Gam @ k.Dk, k.Bk])
    Cu = np.hstack([-k.Dk @ C, -k.Ck])
    return A, B, Cu, -k.Dk


def noise_rms(
    Phi: Matrix, Gam: Matrix, C: Matrix, *, Lc: Matrix, Kc: Matrix, Kdist: Matrix, count: float
) -> FloatArray:
    """RMS current per input for white encoder noise of one count RMS on every output (H2 norm of
    n -> u, row by row, times ``count``); inf for an unstable closed loop."""
    import scipy.linalg

    A, B, Cu, Du = closed_loop_noise_system(Phi, Gam, C, Lc=Lc, Kc=Kc, Kdist=Kdist)
    if np.max(np.abs(np.linalg.eigvals(A))) >= 1.0:
        return np.full(Gam.shape[1], math.inf)
    P = scipy.linalg.solve_discrete_lyapunov(A, B @ B.T)
    var = np.diag(Cu @ P @ Cu.T + Du @ Du.T)
    return np.asarray(np.sqrt(np.maximum(var, 0.0)) * count, dtype=np.float64)


@dataclass(frozen=True)
class Merit:
    """The figures of merit of one (Lc, Kc, Kdist) (see the module docstring); band = the frequencies
    the rejection is asked at."""

    band_hz: FloatArray
    rejection: FloatArray  # sigma_max(w -> y) at band_hz [output unit per input unit]
    peak_S: float
    peak_T: float
    noise_rms_A: FloatArray  # per input
    noise_peak_A: float
    disk_input: tuple[DiskMargin, ...]
    disk_output: tuple[DiskMargin, ...]
    gain_margin_db: float  # worst loop-at-a-time classical margins at the plant input
    phase_margin_deg: float
    delay_margin_s: float
    closed_loop_radius: float
    multiloop_input: MultiloopDiskMargin | None = None  # evaluate(multiloop=True) only
    # per input (loop at a time): gain margin dB, phase margin deg, delay margin s
    input_margins: tuple[tuple[float, float, float], ...] = ()

    @property
    def worst_rejection(self) -> float:
        return float(np.max(self.rejection))

    @property
    def disk_gain_margin_db(self) -> float:
        """The smallest balanced disk gain margin: loop at a time at the plant input and output, and
        the multiloop one at the plant input when computed."""
        values = [d.gain_margin_db for d in self.disk_input + self.disk_output]
        if self.multiloop_input is not None:
            values.append(self.multiloop_input.gain_margin_db)
        return min(values)

    @property
    def disk_phase_margin_deg(self) -> float:
        values = [d.phase_margin_deg for d in self.disk_input + self.disk_output]
        if self.multiloop_input is not None:
            values.append(self.multiloop_input.phase_margin_deg)
        return min(values)


def _diag(F: CMatrix, i: int) -> npt.NDArray[np.complex128]:
    return np.asarray(F[:, i, i], dtype=np.complex128)


def evaluate(
    Phi: Matrix,
    Gam: Matrix,
    Gam_w: Matrix,
    C: Matrix,
    *,
    Lc: Matrix,
    Kc: Matrix,
    Kdist: Matrix,
    period_s: float,
    omega_rad_s: FloatArray,
    band_hz: FloatArray,
    count: float,
    multiloop: bool = False,
) -> Merit:
    """All figures of merit on the grid ``omega_rad_s`` (ascending, ending at Nyquist); with
    ``multiloop`` also the multiloop disk margin at the plant input (on the grid, not refined)."""
    r: LoopResponse = loop_response(
        Phi, Gam, Gam_w, C, Lc=Lc, Kc=Kc, Kdist=Kdist, period_s=period_s, omega_rad_s=omega_rad_s
    )
    band = np.asarray(band_hz, dtype=np.float64).ravel()
    rb = loop_response(
        Phi, Gam, Gam_w, C, Lc=Lc, Kc=Kc, Kdist=Kdist, period_s=period_s, omega_rad_s=2 * math.pi * band
    )
    m, p = Gam.shape[1], C.shape[0]
    w = np.asarray(omega_rad_s, dtype=np.float64)
    disk_in = tuple(disk_margin(_diag(r.Si, i), w) for i in range(m))
    disk_out = tuple(disk_margin(_diag(r.S, i), w) for i in range(p))
    gms, pms, dms = [], [], []
    for i in range(m):
        gm, pm, dm = classical_margins(1.0 / _diag(r.Si, i) - 1.0, w)
        gms.append(gm)
        pms.append(pm)
        dms.append(dm)
    radius = max(
        float(np.max(np.abs(np.linalg.eigvals(feedback_matrix(Phi, Gam, Kc))))),
        float(np.max(np.abs(np.linalg.eigvals(dob_matrix(Phi, Gam, C, Lc, Kdist))))),
    )
    return Merit(
        band_hz=band,
        rejection=max_singular_value(rb.disturbance),
        peak_S=float(np.max(max_singular_value(r.S))),
        peak_T=float(np.max(max_singular_value(r.T))),
        noise_rms_A=noise_rms(Phi, Gam, C, Lc=Lc, Kc=Kc, Kdist=Kdist, count=count),
        noise_peak_A=float(np.max(max_singular_value(r.K @ r.S))) * count,
        disk_input=disk_in,
        disk_output=disk_out,
        gain_margin_db=min(gms, key=abs),
        phase_margin_deg=min(pms, key=abs),
        delay_margin_s=min(dms),
        closed_loop_radius=radius,
        multiloop_input=multiloop_disk_margin(r.Si, w, where="plant input") if multiloop else None,
        input_margins=tuple(zip(gms, pms, dms, strict=True)),
    )


def analysis_grid_rad_s(period_s: float, points: int = 600) -> FloatArray:
    """Log-spaced angular frequencies from 1e-4 of Nyquist to Nyquist, plus a linear tail near
    Nyquist (where noise-to-current and |S| peak)."""
    nyq = math.pi / period_s
    grid = np.unique(np.concatenate([np.logspace(math.log10(nyq) - 4.0, math.log10(nyq), points),
                                     np.linspace(0.5 * nyq, nyq, points // 4)]))  # fmt: skip
    return np.asarray(grid, dtype=np.float64)


@dataclass(frozen=True)
class DiskBounds:
    """Lower bounds on the balanced multiloop disk margin at the plant input (None: not imposed) and
    whether they were configured (``design.optimize.min_disk_*``) or are the defaults."""

    gain_margin_db: float | None
    phase_margin_deg: float | None
    configured: bool

    @classmethod
    def from_config(cls, gain_margin_db: float | None, phase_margin_deg: float | None) -> DiskBounds:
        if gain_margin_db is None and phase_margin_deg is None:
            b = ROBUSTNESS_BOUNDS
            return cls(b["min_disk_gain_margin_dB"], b["min_disk_phase_margin_deg"], False)
        return cls(gain_margin_db, phase_margin_deg, True)


def plant_input_multiloop(design: Design, Kdist: Matrix, omega_rad_s: FloatArray) -> MultiloopDiskMargin:
    """The balanced multiloop disk margin at the plant input (``multiloop``) of the run-time loop."""

    def si(x: FloatArray) -> CMatrix:
        return loop_response(
            design.Phi, design.Gam, design.Gam_w, design.C, Lc=design.Lc, Kc=design.Kc, Kdist=Kdist,
            period_s=design.period_s, omega_rad_s=x,
        ).Si  # fmt: skip

    return multiloop_disk_margin(si(omega_rad_s), omega_rad_s, where="plant input", response=si)


def multiloop_warnings(m: MultiloopDiskMargin, bounds: DiskBounds, which: str) -> list[str]:
    """Messages for a multiloop disk margin below ``bounds``."""
    out = []

    def src(key: str) -> str:
        name = f"design.optimize.min_disk_{key}"
        return name if bounds.configured else f"default bound; {name} sets it"

    tail = f" at {m.at_hz:.3g} Hz (alpha {m.alpha:.3g}; every input perturbed at once)"
    tol = 1.0 - DISK_BOUND_TOLERANCE
    if bounds.gain_margin_db is not None and m.gain_margin_db < bounds.gain_margin_db * tol:
        out.append(
            f"robustness {which}: multiloop disk gain margin at the plant input +/-{m.gain_margin_db:.3g} dB "
            f"< {bounds.gain_margin_db:g} dB ({src('gain_margin_dB')}){tail}"
        )
    if bounds.phase_margin_deg is not None and m.phase_margin_deg < bounds.phase_margin_deg * tol:
        out.append(
            f"robustness {which}: multiloop disk phase margin at the plant input +/-{m.phase_margin_deg:.3g} "
            f"deg < {bounds.phase_margin_deg:g} deg ({src('phase_margin_deg')}){tail}"
        )
    return out


def design_warnings(
    design: Design, dob_enabled: bool, counts_per_unit: float, *, disk_bounds: DiskBounds | None = None
) -> tuple[str, ...]:
    """Messages for every violated ``ROBUSTNESS_BOUNDS`` entry of the loop that will run (with the
    DOB when ``dob_enabled``), for a DOB that cuts the delay margin below one sample, and for a
    balanced multiloop disk margin at the plant input below ``disk_bounds`` (default: the
    ``ROBUSTNESS_BOUNDS`` disk entries). The multiloop check runs for multi-input plants, and for a
    single-input plant only when the bounds were configured (SISO designs are otherwise covered by
    the gain and phase margin bounds, as before)."""
    Kd = design.Kdist if dob_enabled else np.zeros_like(design.Kdist)
    w = analysis_grid_rad_s(design.period_s)

    def merit(K: Matrix) -> Merit:
        return evaluate(
            design.Phi, design.Gam, design.Gam_w, design.C, Lc=design.Lc, Kc=design.Kc, Kdist=K,
            period_s=design.period_s, omega_rad_s=w, band_hz=np.array([1.0]), count=1.0 / counts_per_unit,
        )  # fmt: skip

    m = merit(Kd)
    if not m.closed_loop_radius < 1.0:
        return ()  # refused by the Theorem-1 gate
    b = ROBUSTNESS_BOUNDS
    which = "with the DOB" if dob_enabled else "without the DOB"

    def at(k: int, value: float) -> str:
        """Which input sets a loop-at-a-time margin (several inputs only)."""
        if design.n_inputs == 1:
            return ""
        i = next(i for i, row in enumerate(m.input_margins) if row[k] == value)
        name = design.input_names[i] if i < len(design.input_names) else ""
        return f" at input {i + 1}{f' ({name})' if name else ''} (loop at a time)"

    out = []
    if m.peak_S > b["max_peak_S"]:
        out.append(f"robustness {which}: peak |S| = {m.peak_S:.3g} > {b['max_peak_S']:g}")
    if abs(m.gain_margin_db) < b["min_gain_margin_dB"]:
        out.append(
            f"robustness {which}: gain margin {m.gain_margin_db:.3g} dB < {b['min_gain_margin_dB']:g} dB"
            + at(0, m.gain_margin_db)
        )
    if m.phase_margin_deg < b["min_phase_margin_deg"]:
        out.append(
            f"robustness {which}: phase margin {m.phase_margin_deg:.3g} deg "
            f"< {b['min_phase_margin_deg']:g} deg" + at(1, m.phase_margin_deg)
        )
    dm_samples = m.delay_margin_s / design.period_s
    if dm_samples < b["min_delay_margin_samples"]:
        cause = ""
        if dob_enabled:
            off = merit(np.zeros_like(design.Kdist)).delay_margin_s / design.period_s
            if off >= b["min_delay_margin_samples"]:
                cause = f" (the DOB cuts it from {off:.2f} samples)"
        out.append(
            f"robustness {which}: delay margin {1e6 * m.delay_margin_s:.0f} us = {dm_samples:.2f} "
            f"samples{at(2, m.delay_margin_s)} < {b['min_delay_margin_samples']:g} sample{cause}"
        )
    bounds = disk_bounds if disk_bounds is not None else DiskBounds.from_config(None, None)
    if design.n_inputs > 1 or bounds.configured:
        out += multiloop_warnings(plant_input_multiloop(design, Kd, w), bounds, which)
    return tuple(out)
