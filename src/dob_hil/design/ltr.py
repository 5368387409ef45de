"""Loop transfer recovery at the plant output (paper sec. 3.4): how close the loop gets to the target.

For each q, Kc(q) solves the feedback DARE (eq. 10-11) with R1 = q C'C and the given R2. The loop is
broken at the plant output with the estimator and Kc(q) in place and the DOB off (the paper designs
Kc for the "fictitious system" of its Figure 3, where the DOB has removed the disturbance):

    Lo_q(z) = P(z) K_q(z)          (see ``loops``: K from Ak, Bk, Ck, Dk with Kdist = 0)
    Gtl(z)  = C (zI - Phi)^-1 Phi Lc   (eq. 8)

and as q grows Lo_q -> Gtl when the plant has no zeros outside the unit circle and C Gam has full rank.
Per q the table gives, over the frequency grid up to Nyquist:

* ``max_relative_error`` = max_w sigma_max(Lo_q - Gtl) / sigma_max(Gtl)
* ``max_weighted_error`` = max_w sigma_max(E (I + Gtl)^-1), E = Lo_q - Gtl: the recovery error seen
  through the target's sensitivity. Since I + Lo_q = (I + E (I + Gtl)^-1)(I + Gtl), a value below 1
  (with Lo_q and Gtl having equally many unstable poles) means the recovered loop is closed-loop stable
  whenever the target loop is.
* ``relative_error_at_crossover``: the relative error at the target's gain crossover (sigma_max(Gtl)
  = 1, where robustness is decided); None if Gtl does not cross 1 on the grid.
* ``recovered_to_Hz``: the highest frequency up to which the relative error stays below 10 %
  (None: not even at the lowest grid frequency).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from dob_hil.design.linalg import CMatrix, Matrix, eigenvalue_magnitudes, max_singular_value
from dob_hil.design.loops import loop_response, target_loop
from dob_hil.design.riccati import solve_feedback_dare

DEFAULT_LTR_Q_VALUES: tuple[float, ...] = tuple(float(10.0**k) for k in range(0, 13, 2))
RECOVERED_TOLERANCE = 0.1


@dataclass(frozen=True)
class LtrRow:
    label: str
    q: float | None
    Kc: Matrix
    feedback_radius: float
    max_relative_error: float
    max_weighted_error: float
    relative_error_at_crossover: float | None
    recovered_to_hz: float | None
    Lo: CMatrix

    def as_dict(self) -> dict[str, object]:
        return {
            "label": self.label,
            "q": self.q,
            "Kc": self.Kc.tolist(),
            "feedback_radius": self.feedback_radius,
            "max_relative_error": self.max_relative_error,
            "max_weighted_error": self.max_weighted_error,
            "relative_error_at_crossover": self.relative_error_at_crossover,
            "recovered_to_Hz": self.recovered_to_hz,
        }


@dataclass(frozen=True)
class LtrReport:
    omega_rad_s: npt.NDArray[np.float64]
    Gtl: CMatrix
    R2: Matrix
    rows: tuple[LtrRow, ...]


def _row(
    label: str,
    q: float | None,
    Kc: Matrix,
    *,
    Phi: Matrix,
    Gam: Matrix,
    C: Matrix,
    Lc: Matrix,
    period_s: float,
    w: npt.NDArray[np.float64],
    Gtl: CMatrix,
) -> LtrRow:
    zeros = np.zeros((Gam.shape[1], Phi.shape[0]))
    Lo = loop_response(Phi, Gam, Gam, C, Lc=Lc, Kc=Kc, Kdist=zeros, period_s=period_s, omega_rad_s=w).Lo
    E = Lo - Gtl
    gtl = max_singular_value(Gtl)
    rel = max_singular_value(E) / np.maximum(gtl, 1e-300)
    cross = np.nonzero((gtl[:-1] - 1.0) * (gtl[1:] - 1.0) <= 0.0)[0]
    at_cross = float(rel[cross[0]]) if cross.size else None
    p = C.shape[0]
    weighted = max_singular_value(E @ np.linalg.inv(np.eye(p) + Gtl))
    bad = np.nonzero(rel > RECOVERED_TOLERANCE)[0]
    if bad.size == 0:
        recovered: float | None = float(w[-1] / (2 * np.pi))
    elif bad[0] == 0:
        recovered = None
    else:
        recovered = float(w[bad[0] - 1] / (2 * np.pi))
    return LtrRow(
        label=label,
        q=q,
        Kc=Kc,
        feedback_radius=max(eigenvalue_magnitudes(Phi - Gam @ Kc)),
        max_relative_error=float(np.max(rel)),
        max_weighted_error=float(np.max(weighted)),
        relative_error_at_crossover=at_cross,
        recovered_to_hz=recovered,
        Lo=Lo,
    )


def ltr_report(
    Phi: Matrix,
    Gam: Matrix,
    C: Matrix,
    Lc: Matrix,
    *,
    Kc_design: Matrix,
    R2: Matrix,
    q_values: tuple[float, ...],
    period_s: float,
    omega_rad_s: npt.ArrayLike,
) -> LtrReport:
    """The LTR table for ``q_values`` (R1 = q C'C, R2) plus a last row for the design's own Kc."""
    w = np.asarray(omega_rad_s, dtype=np.float64).ravel()
    Gtl = target_loop(Phi, C, Lc, period_s, w)
    rows = []
    for q in q_values:
        Kc = solve_feedback_dare(Phi, Gam, q * (C.T @ C), R2).gain
        rows.append(
            _row(f"q={q:g}", float(q), Kc, Phi=Phi, Gam=Gam, C=C, Lc=Lc, period_s=period_s, w=w, Gtl=Gtl)
        )
    rows.append(
        _row("design Kc", None, Kc_design, Phi=Phi, Gam=Gam, C=C, Lc=Lc, period_s=period_s, w=w, Gtl=Gtl)
    )
    return LtrReport(w, Gtl, R2, tuple(rows))
