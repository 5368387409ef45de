"""Classical gain and phase margins of a scalar discrete-time loop l(e^{j w Ts}), found on a frequency
grid up to the Nyquist frequency and refined by root finding on the exact response.

* Gain margin: at each phase crossover (l real and negative, -a) the loop tolerates a gain factor
  1/a; the reported margin is the crossover whose factor is closest to 1 (in dB: negative means a
  gain *reduction* of that size destabilises a conditionally stable loop). None: no crossover.
* Phase margin: at each gain crossover (|l| = 1) the margin is angle(-l) in (-180, 180] degrees; the
  reported one is the smallest in magnitude. None: no crossover.

For MIMO loops use :func:`dob_hil.design.loops.loop_at_a_time` for one channel with the others closed.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

LoopFn = Callable[[npt.NDArray[np.float64]], npt.NDArray[np.complex128]]


@dataclass(frozen=True)
class Margins:
    gain_margin_db: float | None
    gain_crossover_hz: float | None  # frequency of the phase crossover that sets the gain margin
    phase_margin_deg: float | None
    phase_crossover_hz: float | None  # frequency of the gain crossover that sets the phase margin

    def as_dict(self) -> dict[str, float | None]:
        return {
            "gain_margin_dB": self.gain_margin_db,
            "gain_margin_at_Hz": self.gain_crossover_hz,
            "phase_margin_deg": self.phase_margin_deg,
            "phase_margin_at_Hz": self.phase_crossover_hz,
        }


def _refine(fn: Callable[[float], float], a: float, b: float) -> float:
    import scipy.optimize

    fa, fb = fn(a), fn(b)
    if fa == 0.0:
        return a
    if fb == 0.0 or fa * fb > 0.0:
        return b
    return float(scipy.optimize.brentq(fn, a, b, xtol=1e-12 * b, rtol=1e-13))


def loop_margins(loop: LoopFn, omega_rad_s: npt.NDArray[np.float64]) -> Margins:
    """Margins of the scalar loop ``loop(omega) -> l`` over the ascending grid ``omega_rad_s`` whose
    last point should be the Nyquist frequency."""
    w = np.asarray(omega_rad_s, dtype=np.float64)
    lw = loop(w)

    def one(x: float) -> complex:
        return complex(loop(np.array([x]))[0])

    # Phase crossovers: Im l changes sign where Re l < 0; at Nyquist l is real for a real system.
    gm_best: tuple[float, float] | None = None
    im = lw.imag
    candidates = [i for i in range(w.size - 1) if im[i] == 0.0 or im[i] * im[i + 1] < 0.0]
    points = [_refine(lambda x: one(x).imag, float(w[i]), float(w[i + 1])) for i in candidates]
    if lw[-1].real < 0.0 and abs(lw[-1].imag) <= 1e-9 * max(abs(lw[-1]), 1e-300):
        points.append(float(w[-1]))
    for x in points:
        val = one(x)
        if val.real < 0.0:
            gm_db = -20.0 * math.log10(-val.real)
            if gm_best is None or abs(gm_db) < abs(gm_best[0]):
                gm_best = (gm_db, x)
    # Gain crossovers: |l| - 1 changes sign.
    pm_best: tuple[float, float] | None = None
    mag = np.abs(lw) - 1.0
    for i in range(w.size - 1):
        if mag[i] == 0.0 or mag[i] * mag[i + 1] < 0.0:
            x = _refine(lambda x: abs(one(x)) - 1.0, float(w[i]), float(w[i + 1]))
            pm = math.degrees(np.angle(-one(x)))
            if pm_best is None or abs(pm) < abs(pm_best[0]):
                pm_best = (pm, x)
    two_pi = 2.0 * math.pi
    return Margins(
        gain_margin_db=None if gm_best is None else gm_best[0],
        gain_crossover_hz=None if gm_best is None else gm_best[1] / two_pi,
        phase_margin_deg=None if pm_best is None else pm_best[0],
        phase_crossover_hz=None if pm_best is None else pm_best[1] / two_pi,
    )
