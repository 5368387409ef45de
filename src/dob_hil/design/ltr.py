"""Loop transfer recovery at the plant output (paper sec. 3.4): how close the loop gets to the target.

For each q, Kc(q) solves the feedback DARE (eq. 10-11) with R1 = q C'C and the given R2. The loop is
broken at the plant output with the estimator and Kc(q) in place and the DOB off (the paper designs
Kc for the "fictitious system" of its Figure 3, where the DOB has removed the disturbance):

    Lo_q(z) = P(z) K_q(z)          (see ``loops``: K from Ak, Bk, Ck, Dk with Kdist = 0)
    Gtl(z)  = C (zI - Phi)^-1 Phi Lc   (eq. 8)

and as q grows Lo_q -> Gtl when the plant has no zeros outside the unit circle and C Gam has full rank.
Per q the table gives, over the frequency grid up to Nyquist:

* ``max_relative_error`` = max_w sigma_max(Lo_q - Gtl) / sigma_max(Gtl) for one output; for several
  outputs the direction-aware (multiplicative) error max_w sigma_max((Lo_q - Gtl) Gtl^-1), which for
  one output is the same number. sigma_max(E) / sigma_max(Gtl) would call a 2x2 loop "recovered"
  while its weak direction (sigma_min(Gtl) << sigma_max(Gtl)) is still off by more than 10 %.
* ``max_weighted_error`` = max_w sigma_max(E (I + Gtl)^-1), E = Lo_q - Gtl: the recovery error seen
  through the target's sensitivity. Since I + Lo_q = (I + E (I + Gtl)^-1)(I + Gtl), a value below 1
  (with Lo_q and Gtl having equally many unstable poles) means the recovered loop is closed-loop stable
  whenever the target loop is.
* ``relative_error_at_crossover``: the relative error at the target's gain crossover (sigma_max(Gtl)
  = 1, where robustness is decided); None if Gtl does not cross 1 on the grid.
* ``recovered_to_Hz``: the highest frequency up to which the relative error stays below 10 %
  (None: not even at the lowest grid frequency).
* ``band_relative_error``: the max relative error inside the band the user cares about
  (``design.feedback.ltr_band_hz``; default from the lowest grid frequency up to twice the target's
  gain crossover) and ``recovered``: that error is below 10 %.

The q sequence is extended by factors of 10 past the configured values until a row recovers in the
band, up to ``MAX_Q`` (or the DARE fails): the table always ends with recovery or a stated reason.
Recovery cannot happen when C Gam has rank < p (an input delay, or relative degree above one: the
loop's high-frequency roll-off cannot match Gtl's) or the plant has zeros outside the unit circle; a
zero near z = -1 (the ZOH sampling zero) is recovered only by cancelling it with a feedback pole near
-1, i.e. a command that alternates sign each sample -- ``obstructions`` and ``notes`` say so.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from dob_hil.design.linalg import CMatrix, Matrix, eigenvalue_magnitudes, max_singular_value
from dob_hil.design.loops import loop_response, target_loop
from dob_hil.design.riccati import solve_feedback_dare
from dob_hil.errors import DesignError

DEFAULT_LTR_Q_VALUES: tuple[float, ...] = tuple(float(10.0**k) for k in range(0, 13, 2))
RECOVERED_TOLERANCE = 0.1
ERROR_SISO = "sigma_max(Lo_q - Gtl) / sigma_max(Gtl)"
ERROR_MIMO = "sigma_max((Lo_q - Gtl) Gtl^-1)"


def relative_error(E: CMatrix, Gtl: CMatrix) -> npt.NDArray[np.float64]:
    """The recovery error per frequency (module docstring): |E| / |Gtl| for one output, else
    sigma_max(E Gtl^-1) (E Gtl^-1 from a linear solve; the pseudo-inverse where Gtl is singular)."""
    if Gtl.shape[-1] == 1:
        return np.asarray(max_singular_value(E) / np.maximum(max_singular_value(Gtl), 1e-300))
    Gt = np.swapaxes(Gtl, -1, -2)
    try:
        X = np.swapaxes(np.linalg.solve(Gt, np.swapaxes(E, -1, -2)), -1, -2)
    except np.linalg.LinAlgError:
        X = E @ np.linalg.pinv(Gtl)
    return np.asarray(max_singular_value(X), dtype=np.float64)


def error_definition(p: int) -> str:
    return ERROR_SISO if p == 1 else ERROR_MIMO


MAX_Q = 1e16
SAMPLING_ZERO_RADIUS = 0.9


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
    band_relative_error: float = float("nan")
    recovered: bool = False

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
            "band_relative_error": self.band_relative_error,
            "recovered_in_band": self.recovered,
        }


@dataclass(frozen=True)
class LtrReport:
    omega_rad_s: npt.NDArray[np.float64]
    Gtl: CMatrix
    R2: Matrix
    rows: tuple[LtrRow, ...]
    band_hz: tuple[float, float] = (0.0, 0.0)
    recovered_at_q: float | None = None
    obstructions: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()


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
    band: npt.NDArray[np.bool_],
) -> LtrRow:
    zeros = np.zeros((Gam.shape[1], Phi.shape[0]))
    Lo = loop_response(Phi, Gam, Gam, C, Lc=Lc, Kc=Kc, Kdist=zeros, period_s=period_s, omega_rad_s=w).Lo
    E = Lo - Gtl
    gtl = max_singular_value(Gtl)
    rel = relative_error(E, Gtl)
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
        band_relative_error=float(np.max(rel[band])),
        recovered=bool(np.max(rel[band]) <= RECOVERED_TOLERANCE),
    )


def transmission_zeros(Phi: Matrix, Gam: Matrix, C: Matrix) -> npt.NDArray[np.complex128]:
    """Finite transmission zeros of a square system (generalised eigenvalues of the Rosenbrock
    pencil); empty for a non-square one."""
    import scipy.linalg

    N, m, p = Phi.shape[0], Gam.shape[1], C.shape[0]
    if m != p:
        return np.zeros(0, dtype=np.complex128)
    a = np.block([[Phi, Gam], [C, np.zeros((p, m))]])
    b = np.block([[np.eye(N), np.zeros((N, m))], [np.zeros((p, N + m))]])
    ev = scipy.linalg.eigvals(a, b)
    return np.asarray(ev[np.isfinite(ev) & (np.abs(ev) < 1e8)], dtype=np.complex128)


def recovery_obstructions(Phi: Matrix, Gam: Matrix, C: Matrix) -> tuple[list[str], list[str]]:
    """(obstructions, notes): why Lo_q cannot reach Gtl, and what recovery costs."""
    out, notes = [], []
    p = C.shape[0]
    rank = int(np.linalg.matrix_rank(C @ Gam, tol=1e-12 * max(1.0, float(np.linalg.norm(C @ Gam)))))
    if rank < p:
        out.append(
            f"C Gam has rank {rank} < {p} (an input delay, or relative degree above one): the recovered "
            "loop keeps an extra roll-off that Gtl does not have"
        )
    for z in transmission_zeros(Phi, Gam, C):
        if abs(z) >= 1.0:
            out.append(f"non-minimum-phase zero at z = {z.real:.4g}{z.imag:+.4g}j: recovery would cancel it")
        elif z.real < 0 and abs(z) >= SAMPLING_ZERO_RADIUS:
            notes.append(
                f"zero at z = {z.real:.4g}{z.imag:+.4g}j (the sampling zero): recovery places a feedback "
                "pole on it, a mode that alternates sign each sample (command chatter)"
            )
    return out, notes


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
    band_hz: tuple[float, float] | None = None,
    extend: bool = True,
) -> LtrReport:
    """The LTR table for ``q_values`` (R1 = q C'C, R2), extended (``extend``) until recovery in the
    band or a stated reason, plus a last row for the design's own Kc."""
    w = np.asarray(omega_rad_s, dtype=np.float64).ravel()
    f = w / (2 * np.pi)
    Gtl = target_loop(Phi, C, Lc, period_s, w)
    if band_hz is None:
        g = max_singular_value(Gtl)
        cross = np.nonzero((g[:-1] - 1.0) * (g[1:] - 1.0) <= 0.0)[0]
        hi = min(2.0 * float(f[cross[0]]), float(f[-1])) if cross.size else float(f[-1])
        band_hz = (float(f[0]), hi)
    band = (f >= band_hz[0] * (1 - 1e-12)) & (f <= band_hz[1] * (1 + 1e-12))
    if not band.any():
        band = np.abs(f - band_hz[1]) == np.min(np.abs(f - band_hz[1]))
    obstructions, notes = recovery_obstructions(Phi, Gam, C)
    kw = {"Phi": Phi, "Gam": Gam, "C": C, "Lc": Lc, "period_s": period_s, "w": w, "Gtl": Gtl, "band": band}

    def row(q: float) -> LtrRow | None:
        try:
            Kc = solve_feedback_dare(Phi, Gam, q * (C.T @ C), R2).gain
        except DesignError as exc:
            notes.append(f"q = {q:g}: {exc}")
            return None
        return _row(f"q={q:g}", float(q), Kc, **kw)  # type: ignore[arg-type]

    rows = [r for r in (row(float(q)) for q in q_values) if r is not None]
    q = float(max(q_values)) if q_values else 1.0
    while extend and not any(r.recovered for r in rows) and q * 10.0 <= MAX_Q and not obstructions:
        q *= 10.0
        r = row(q)
        if r is None:
            break
        rows.append(r)
    recovered_at = next((r.q for r in rows if r.recovered), None)
    if recovered_at is None:
        why = "; ".join(obstructions) if obstructions else f"not within q <= {MAX_Q:g}"
        notes.append(f"no q recovers Gtl within 10 % in {band_hz[0]:.3g}-{band_hz[1]:.3g} Hz: {why}")
    rows.append(_row("design Kc", None, Kc_design, **kw))  # type: ignore[arg-type]
    return LtrReport(w, Gtl, R2, tuple(rows), band_hz, recovered_at, tuple(obstructions), tuple(notes))
