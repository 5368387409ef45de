"""PNG plots of a design analysis (matplotlib, Agg backend, imported here only).

* ``sensitivity.png``: |S| and |T| at the plant output in dB vs frequency in Hz up to Nyquist, with and
  without the DOB (the paper's Figure 5; sigma_max for MIMO loops).
* ``disturbance.png``: input disturbance w -> output y, with and without the DOB.
* ``dob_locus.png``: eigenvalue magnitudes of Phi - Phi Lc C - Gam Kdist Lc C along the DOB gain
  direction, with the design, the fastest gain and the stability limit marked.
* ``ltr.png``: the target loop Gtl and the recovered loops Lo_q for the LTR sequence of q.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dob_hil.design.analysis import DesignAnalysis
from dob_hil.design.linalg import max_singular_value


def _db(x: Any) -> Any:
    return 20.0 * np.log10(np.maximum(np.asarray(x, dtype=np.float64), 1e-300))


def write_plots(a: DesignAnalysis, out_dir: Path) -> list[Path]:
    """Write the four PNGs into ``out_dir`` and return their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    d = a.result.design
    f = a.frequency_hz
    nyq = 0.5e9 / d.period_ns
    paths: list[Path] = []
    mimo = d.n_outputs > 1 or d.n_inputs > 1
    tag = " (sigma_max)" if mimo else ""

    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.semilogx(f, _db(max_singular_value(a.dob_on.response.S)), "b-", label=f"S, DOB on{tag}")
    ax.semilogx(f, _db(max_singular_value(a.dob_on.response.T)), "r-", label=f"T, DOB on{tag}")
    ax.semilogx(f, _db(max_singular_value(a.dob_off.response.S)), "b--", label="S, DOB off")
    ax.semilogx(f, _db(max_singular_value(a.dob_off.response.T)), "r--", label="T, DOB off")
    ax.set(
        xlabel="frequency [Hz]", ylabel="magnitude [dB]", title=f"{d.name}: sensitivity at the plant output"
    )
    ax.set_xlim(f[0], nyq)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    paths.append(out_dir / "sensitivity.png")
    fig.savefig(paths[-1], dpi=110, bbox_inches="tight")
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.semilogx(f, _db(max_singular_value(a.dob_on.response.disturbance)), "b-", label="DOB on")
    ax.semilogx(f, _db(max_singular_value(a.dob_off.response.disturbance)), "k--", label="DOB off")
    ax.set(
        xlabel="frequency [Hz]",
        ylabel=f"|y / w| [dB, {d.output_unit} per {d.input_unit}]",
        title=f"{d.name}: input disturbance to output{tag}",
    )
    ax.set_xlim(f[0], nyq)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    paths.append(out_dir / "disturbance.png")
    fig.savefig(paths[-1], dpi=110, bbox_inches="tight")
    plt.close(fig)

    dob = a.result.dob
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.plot(a.locus_gain, a.locus_magnitudes, color="0.6", lw=0.8)
    ax.plot(a.locus_gain, a.locus_magnitudes.max(axis=1), "b-", label="spectral radius")
    ax.axhline(1.0, color="r", lw=0.8, label="stability limit")
    ax.axvline(dob.gain, color="g", ls="--", label=f"design k = {dob.gain:.4g}")
    ax.axvline(dob.k_min_radius, color="m", ls=":", label=f"fastest k = {dob.k_min_radius:.4g}")
    unit = "DOB loop DC gain" if dob.direction_kind == "pinv(H(1))" else "scale of Kdist Lc"
    ax.set(
        xlabel=f"k ({unit}; Kdist Lc = k {dob.direction_kind})",
        ylabel="|eig(Phi - Phi Lc C - Gam Kdist Lc C)|",
        title=f"{d.name}: DOB gain locus",
    )
    ax.grid(True, alpha=0.3)
    ax.legend()
    paths.append(out_dir / "dob_locus.png")
    fig.savefig(paths[-1], dpi=110, bbox_inches="tight")
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.semilogx(f, _db(max_singular_value(a.ltr.Gtl)), "k-", lw=2.0, label="target Gtl")
    for row in a.ltr.rows:
        style = "g--" if row.q is None else "-"
        ax.semilogx(f, _db(max_singular_value(row.Lo)), style, lw=1.0, label=row.label)
    ax.set(
        xlabel="frequency [Hz]",
        ylabel="|Lo| [dB]",
        title=f"{d.name}: loop transfer recovery at the plant output",
    )
    ax.set_xlim(f[0], nyq)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    paths.append(out_dir / "ltr.png")
    fig.savefig(paths[-1], dpi=110, bbox_inches="tight")
    plt.close(fig)
    return paths
