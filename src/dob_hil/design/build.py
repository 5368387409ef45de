"""``build_design(config) -> Design``: the whole design of the paper from a TOML config.

1. ZOH-discretise the continuous plant at ``plant.period_us`` and augment an input delay of d samples
   (``discretize``); everything after works on the augmented model (Phi, Gam, C).
2. Estimator gain Lc: ``design.estimator.Lc`` if given, else the DARE of eq. 6-7 with ``Gam1`` (default
   Gam_w, i.e. the residual disturbance enters at the plant input) and ``D1`` (default I_p).
3. Feedback gain Kc: ``design.feedback.Kc`` if given, else the DARE of eq. 10-11 with R1 = q C'C
   (``q`` default 1) and ``R2`` (default I_m).
4. DOB gain Kdist: ``design.dob.Kdist`` if given, else ``design.dob.method``/``gain`` (``dob``).
   With ``design.dob.method = "optimize"`` (or ``optimize=True``) Kdist -- and with
   ``design.optimize.tune = "all"`` Lc and Kc too -- come from :mod:`dob_hil.design.optimize`.
5. Theorem 1: the closed-loop eigenvalues are those of the feedback matrix and of the DOB matrix
   (DOB on, ``dob_enabled``, default ``run.dob_enabled``) or the estimator matrix (DOB off); each must
   be stable, otherwise DesignError names the matrix and its spectral radius.
6. Robustness: :func:`dob_hil.design.robustness.design_warnings` lists every violated robustness bound
   (peak |S|, margins, delay margin, the multiloop disk margin at the plant input of a multi-input
   plant against ``design.optimize.min_disk_*`` or the defaults) and a weak DOB; they are in
   ``DesignResult.warnings`` and issued as :class:`dob_hil.design.robustness.DesignWarning`
   (``warnings.warn``) so ``run`` shows them too.
"""

from __future__ import annotations

import contextlib
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING

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
from dob_hil.design.linalg import Matrix
from dob_hil.design.riccati import DareSolution, solve_estimator_dare, solve_feedback_dare
from dob_hil.design.robustness import DesignWarning, DiskBounds, design_warnings
from dob_hil.design.theorem1 import EXPRESSIONS, spectral_radii, unstable_parts
from dob_hil.errors import DesignError

if TYPE_CHECKING:
    from dob_hil.design.optimize import OptimizeResult

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
    warnings: tuple[str, ...] = ()
    optimized: OptimizeResult | None = None


def design_with_diagnostics(
    config: Config, *, dob_enabled: bool | None = None, optimize: bool = False, locus: bool = True
) -> DesignResult:
    """Everything :func:`build_design` does, returning the diagnostics too. ``optimize`` runs the
    ``optimize`` method whatever ``design.dob`` says (``dob-hil design --optimize``); ``locus=False``
    skips the DOB gain locus of an explicit Kdist (``build_design``: not needed to run)."""
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

    optimized: OptimizeResult | None = None
    if optimize or dc.dob.method == "optimize":
        from dob_hil.design.optimize import optimize_design

        optimized = optimize_design(config, Phi, Gam, Gam_w, C, Lc=Lc, Kc=Kc)
        Lc, Kc = optimized.Lc, optimized.Kc
        dob = design_dob(
            Phi, Gam, Gam_w, C, Lc, Kdist=optimized.Kdist, method=None, gain=None, explicit_label="optimize"
        )
        sources["Kdist"] = f"optimize: {optimized.summary}"
        if optimized.tune == "all":
            sources["Lc"] = sources["Kc"] = "optimize (tune = all), started from " + sources["Lc"]
    else:
        dob = design_dob(
            Phi, Gam, Gam_w, C, Lc, Kdist=dc.dob.Kdist, method=dc.dob.method, gain=dc.dob.gain, locus=locus
        )
    if dob.method == "explicit":
        sources["Kdist"] = "explicit (design.dob.Kdist)"
    elif dob.method == "optimize":
        pass
    else:
        sources["Kdist"] = (
            f"method {dob.method}: Kdist Lc = {dob.gain:.6g} pinv(H(1)), Kdist = Kdist Lc pinv(Lc)"
        )

    radii = spectral_radii(Phi, Gam, C, Lc=Lc, Kc=Kc, Kdist=dob.Kdist)
    problems = unstable_parts(radii, dob_on)
    if problems:
        hint = ""
        if any(s.startswith("dob:") for s in problems) and dob.k_max is None and not locus:
            with contextlib.suppress(DesignError):  # the stable range for the message (error path only)
                dob = design_dob(Phi, Gam, Gam_w, C, Lc, Kdist=dob.Kdist, method=None, gain=None)
        if any(s.startswith("dob:") for s in problems) and dob.k_max is not None:
            hint = (
                f" (stable DOB gains along {dob.direction_kind}: 0 <= k < {dob.k_max:.4g}; "
                f"this design has k = {dob.gain:.4g})"
            )
        rho_est = max(radii["estimator"])
        if dob_on and rho_est >= 1.0:
            hint += f" (the estimator alone is unstable too: rho({EXPRESSIONS['estimator']}) = {rho_est:.4g})"
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
    disk = DiskBounds.from_config(dc.optimize.min_disk_gain_margin_dB, dc.optimize.min_disk_phase_margin_deg)
    notes = dob.warnings + design_warnings(
        design, dob_on, config.drive.encoder_counts_per_unit, disk_bounds=disk
    )
    for note in notes:
        warnings.warn(note, DesignWarning, stacklevel=2)
    return DesignResult(design, est_sol, fb_sol, dob, Gam1, D1, q, R2, dob_on, notes, optimized)


def build_design(config: Config, *, dob_enabled: bool | None = None) -> Design:
    """Design Lc, Kc and Kdist for ``config`` (see the module docstring). ``dob_enabled`` overrides
    ``config.run.dob_enabled`` (e.g. ``--no-dob``): only with the DOB on must the dob matrix be stable.
    Raises DesignError for an unstable design (naming the matrix and its spectral radius) or a DARE
    without a solution, and ConfigError for invalid design settings."""
    return design_with_diagnostics(config, dob_enabled=dob_enabled, locus=False).design
