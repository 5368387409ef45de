"""``build_design(config) -> Design``: the whole design of the paper from a TOML config.

1. ZOH-discretise the continuous plant at ``plant.period_us`` and augment an input delay of d samples
   (``discretize``); everything after works on the augmented model (Phi, Gam, C).
2. Estimator gain Lc: ``design.estimator.Lc`` if given, else the DARE of eq. 6-7 with ``Gam1`` (default
   Gam_w, i.e. the residual disturbance enters at the plant input) and ``D1`` (default I_p).
3. Feedback gain Kc: ``design.feedback.Kc`` if given, else the DARE of eq. 10-11 with R1 = q C'C
   (``q`` default 1) and ``R2`` (default I_m).
4. DOB gain Kdist: ``design.dob.Kdist`` if given, else ``design.dob.method``/``gain`` (``dob``).
5. Theorem 1: the estimator and feedback matrices must be stable, and with the DOB enabled
   (``dob_enabled``, default ``run.dob_enabled``) the dob matrix too; otherwise DesignError names the
   matrix and its spectral radius. With the DOB disabled the dob matrix is still reported.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dob_hil.config import Config
from dob_hil.design.artifact import FORMAT_VERSION, Design
from dob_hil.design.discretize import (
    augment_input_delay,
    augmented_state_names,
    disturbance_input_matrix,
    zoh,
)
from dob_hil.design.dob import DobDesign, design_dob
from dob_hil.design.linalg import Matrix, spectral_radius
from dob_hil.design.riccati import DareSolution, solve_estimator_dare, solve_feedback_dare
from dob_hil.design.theorem1 import EXPRESSIONS, estimator_matrix, spectral_radii, unstable_parts
from dob_hil.errors import DesignError

DEFAULT_Q = 1.0


@dataclass(frozen=True)
class DesignResult:
    """A design with its diagnostics: the DARE solutions (None where a gain was given) and the DOB design."""

    design: Design
    estimator_dare: DareSolution | None
    feedback_dare: DareSolution | None
    dob: DobDesign
    Gam1: Matrix | None
    D1: Matrix | None
    q: float | None
    R2: Matrix
    dob_enabled: bool


def _fmt(M: Matrix) -> str:
    return np.array2string(M, precision=5, separator=", ", max_line_width=200).replace("\n", "")


def design_with_diagnostics(config: Config, *, dob_enabled: bool | None = None) -> DesignResult:
    """Everything :func:`build_design` does, returning the diagnostics too."""
    dob_on = config.run.dob_enabled if dob_enabled is None else dob_enabled
    plant, dc = config.plant, config.design
    n, m, p, d = plant.n_states, plant.n_inputs, plant.n_outputs, plant.input_delay_samples
    Phi0, Gam0 = zoh(plant.A, plant.B, plant.period_ns)
    Phi, Gam, C = augment_input_delay(Phi0, Gam0, plant.C, d)
    Gam_w = disturbance_input_matrix(Phi, Gam, n, d)
    sources: dict[str, str] = {}

    est_sol: DareSolution | None = None
    Gam1: Matrix | None = None
    D1: Matrix | None = None
    if dc.estimator.Lc is not None:
        Lc = dc.estimator.Lc
        sources["Lc"] = "explicit (design.estimator.Lc)"
    else:
        Gam1 = dc.estimator.Gam1 if dc.estimator.Gam1 is not None else Gam_w
        D1 = dc.estimator.D1 if dc.estimator.D1 is not None else np.eye(p)
        est_sol = solve_estimator_dare(Phi, C, Gam1, D1)
        Lc = est_sol.gain
        sources["Lc"] = (
            f"DARE eq. 6-7, Gam1 = {'given' if dc.estimator.Gam1 is not None else 'Gam_w (default)'}, "
            f"D1 = {'given' if dc.estimator.D1 is not None else 'I (default)'}"
        )
    rho_est = spectral_radius(estimator_matrix(Phi, C, Lc))
    if not rho_est < 1.0:
        raise DesignError(
            f"estimator: rho({EXPRESSIONS['estimator']}) = {rho_est:.4g} >= 1 (Lc = {_fmt(Lc)})"
        )

    fb_sol: DareSolution | None = None
    q: float | None = None
    R2 = dc.feedback.R2 if dc.feedback.R2 is not None else np.eye(m)
    if dc.feedback.Kc is not None:
        Kc = dc.feedback.Kc
        sources["Kc"] = "explicit (design.feedback.Kc)"
    else:
        q = dc.feedback.q if dc.feedback.q is not None else DEFAULT_Q
        fb_sol = solve_feedback_dare(Phi, Gam, q * (C.T @ C), R2)
        Kc = fb_sol.gain
        sources["Kc"] = (
            f"DARE eq. 10-11, R1 = q C'C with q = {q:g}{'' if dc.feedback.q is not None else ' (default)'}, "
            f"R2 = {'given' if dc.feedback.R2 is not None else 'I (default)'}"
        )

    dob = design_dob(Phi, Gam, Gam_w, C, Lc, Kdist=dc.dob.Kdist, method=dc.dob.method, gain=dc.dob.gain)
    if dob.method == "explicit":
        sources["Kdist"] = "explicit (design.dob.Kdist)"
    else:
        sources["Kdist"] = (
            f"method {dob.method}: Kdist Lc = {dob.gain:.6g} pinv(H(1)), Kdist = Kdist Lc pinv(Lc)"
        )

    radii = spectral_radii(Phi, Gam, C, Lc=Lc, Kc=Kc, Kdist=dob.Kdist)
    problems = unstable_parts(radii, dob_on)
    if problems:
        hint = ""
        if any(s.startswith("dob:") for s in problems) and dob.k_max is not None:
            hint = (
                f" (stable DOB gains along {dob.direction_kind}: 0 <= k < {dob.k_max:.4g}; "
                f"this design has k = {dob.gain:.4g})"
            )
        raise DesignError("; ".join(problems) + hint)

    design = Design(
        format_version=FORMAT_VERSION,
        name=config.name,
        period_ns=plant.period_ns,
        A=plant.A,
        B=plant.B,
        C_cont=plant.C,
        Phi=Phi,
        Gam=Gam,
        C=C,
        Lc=Lc,
        Kc=Kc,
        Kdist=dob.Kdist,
        n_plant_states=n,
        input_delay_samples=d,
        state_names=augmented_state_names(plant.state_names, plant.input_names, d),
        input_names=plant.input_names,
        output_names=plant.output_names,
        input_unit=plant.input_unit,
        output_unit=plant.output_unit,
        spectral_radii=radii,
        gain_sources=sources,
    )
    return DesignResult(design, est_sol, fb_sol, dob, Gam1, D1, q, R2, dob_on)


def build_design(config: Config, *, dob_enabled: bool | None = None) -> Design:
    """Design Lc, Kc and Kdist for ``config`` (see the module docstring). ``dob_enabled`` overrides
    ``config.run.dob_enabled`` (e.g. ``--no-dob``): only with the DOB on must the dob matrix be stable.
    Raises DesignError for an unstable design (naming the matrix and its spectral radius) or a DARE
    without a solution, and ConfigError for invalid design settings."""
    return design_with_diagnostics(config, dob_enabled=dob_enabled).design
