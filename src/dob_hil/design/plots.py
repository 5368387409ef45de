"""PNG plots of a design analysis (matplotlib, Agg backend, imported here only).

* ``sensitivity.png``: left, |S| and |T| at the plant output in dB up to Nyquist, DOB on (solid) and
  off (dashed), peaks and the configured disturbance frequencies marked (the paper's Figure 5;
  sigma_max for MIMO loops); right, noise to current: |K S| times one encoder count [A] (for several
  inputs one curve per input: the 2-norm of row i of K S, the worst direction of the noise).
* ``disturbance.png``: input disturbance w -> output y, with and without the DOB.
* ``dob_filter.png``: the disturbance-to-estimate filter Q(z) (w -> -u_dist), magnitude and phase
  (several inputs: sigma_max, and each input's own Q_ii in magnitude and phase).
* ``dob_locus.png``: eigenvalue magnitudes of Phi - Phi Lc C - Gam Kdist Lc C along the DOB gain
  direction, with the design, the fastest gain and the stability limit marked.
* ``ltr.png``: the target loop Gtl and the loops Lo_q of the LTR sequence of q, with the error band
  (several outputs: sigma_max of each loop, and the target's sigma_min too).
* ``tradeoff.png`` (``dob-hil design --optimize``): best worst-case rejection in the band against the
  RMS noise-to-current bound, from :func:`dob_hil.design.optimize.tradeoff_curve`.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dob_hil.design.analysis import DesignAnalysis
from dob_hil.design.linalg import max_singular_value, min_singular_value

if TYPE_CHECKING:
    from dob_hil.config import Config
    from dob_hil.design.build import DesignResult


def _db(x: Any) -> Any:
    return 20.0 * np.log10(np.maximum(np.asarray(x, dtype=np.float64), 1e-300))


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path, plt: Any) -> Path:
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def _sensitivity(a: DesignAnalysis, out_dir: Path, plt: Any, tag: str) -> Path:
    d = a.result.design
    f = a.frequency_hz
    nyq = 0.5e9 / d.period_ns
    wide = bool(tag)  # MIMO: longer legend entries need room between the panels
    fig, (ax, axn) = plt.subplots(1, 2, figsize=(16 if wide else 13, 4.5),
                                  gridspec_kw={"wspace": 0.55 if wide else 0.25})  # fmt: skip
    for s, style, label in ((a.dob_on, "-", "DOB on"), (a.dob_off, "--", "DOB off")):
        S, T = max_singular_value(s.response.S), max_singular_value(s.response.T)
        ax.semilogx(f, _db(S), "b" + style, label=f"S, {label}{tag}")
        ax.semilogx(f, _db(T), "r" + style, label=f"T, {label}{tag}")
        if d.n_inputs == 1:
            axn.semilogx(f, s.noise_to_current, "k" + style, label=f"{label}: RMS {max(s.noise_rms_A):.3g} A")
            continue
        for i in range(d.n_inputs):  # one curve per input: row i of K S, worst noise direction
            name = d.input_names[i] if i < len(d.input_names) else str(i + 1)
            axn.semilogx(f, s.noise_to_current_per_input[:, i], style, color=f"C{i}",
                         label=f"input {i + 1} ({name}), {label}: RMS {s.noise_rms_A[i]:.3g} A")  # fmt: skip
    for pk, color, name in ((a.dob_on.peak_S, "b", "|S|"), (a.dob_on.peak_T, "r", "|T|")):
        ax.plot([pk.frequency_hz], [_db(pk.value)], color + "o")
        ax.annotate(f"peak {name} {pk.value:.3g}", (pk.frequency_hz, float(_db(pk.value))), fontsize=8,
                    xytext=(4, 4), textcoords="offset points", color=color)  # fmt: skip
    for fr, _ in a.dob_on.disturbance_at:
        ax.axvline(fr, color="0.5", lw=0.8, ls=":")
        ax.annotate(f"{fr:g} Hz", (fr, ax.get_ylim()[0]), fontsize=8, color="0.4", rotation=90,
                    xytext=(2, 4), textcoords="offset points")  # fmt: skip
    ax.set(xlabel="frequency [Hz]", ylabel="magnitude [dB]",
           title=f"{d.name}: S and T at the plant output (to Nyquist, {nyq:.0f} Hz)")  # fmt: skip
    ax.set_xlim(f[0], nyq)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # outside the data
    ylabel = "|u / n| x 1 count [A]" if d.n_inputs == 1 else "||row i of K S|| x 1 count [A]"
    axn.set(xlabel="frequency [Hz]", ylabel=ylabel,
            title="noise to current (one encoder count)")  # fmt: skip
    axn.set_xlim(f[0], nyq)
    axn.grid(True, which="both", alpha=0.3)
    axn.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # outside the data
    return _save(fig, out_dir / "sensitivity.png", plt)


def _disturbance(a: DesignAnalysis, out_dir: Path, plt: Any, tag: str) -> Path:
    d = a.result.design
    f = a.frequency_hz
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.semilogx(f, _db(max_singular_value(a.dob_on.response.disturbance)), "b-", label="DOB on")
    ax.semilogx(f, _db(max_singular_value(a.dob_off.response.disturbance)), "k--", label="DOB off")
    for fr, g in a.dob_on.disturbance_at:
        ax.plot([fr], [_db(g)], "bo")
        ax.annotate(
            f"{fr:g} Hz: {g:.3g}",
            (fr, float(_db(g))),
            fontsize=8,
            xytext=(4, -12),
            textcoords="offset points",
        )
    ax.set(
        xlabel="frequency [Hz]",
        ylabel=f"|y / w| [dB, {d.output_unit} per {d.input_unit}]",
        title=f"{d.name}: input disturbance to output{tag}",
    )
    ax.set_xlim(f[0], 0.5e9 / d.period_ns)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # outside the data
    return _save(fig, out_dir / "disturbance.png", plt)


def _dob_filter(a: DesignAnalysis, out_dir: Path, plt: Any, tag: str) -> Path:
    d = a.result.design
    f = a.frequency_hz
    fig, (ax, axp) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    q = max_singular_value(a.Q)
    q1 = float(np.linalg.svd(a.result.dob.dc_estimate_gain, compute_uv=False)[0])
    ax.semilogx(f, _db(q), "b-", label=f"Q(z){tag}: Q(1) = {q1:.4g}")
    ax.axhline(float(_db(q1)) - 3.0, color="0.5", ls=":", lw=0.8, label="Q(1) - 3 dB")
    ax.set(ylabel="|Q| [dB]", title=f"{d.name}: disturbance-to-estimate filter Q(z) (w -> -u_dist; not T)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # outside the data
    if d.n_inputs == 1:
        axp.semilogx(f, np.degrees(np.unwrap(np.angle(a.Q[:, 0, 0]))), "b-")
    else:  # several inputs: each input's own estimate Q_ii (the off-diagonal entries are cross terms)
        for i in range(d.n_inputs):
            name = d.input_names[i] if i < len(d.input_names) else str(i + 1)
            ax.semilogx(
                f,
                _db(np.abs(a.Q[:, i, i])),
                "--",
                color=f"C{i + 1}",
                label=f"Q_{i + 1}{i + 1}, input {i + 1} ({name})",
            )
            axp.semilogx(f, np.degrees(np.unwrap(np.angle(a.Q[:, i, i]))), "--", color=f"C{i + 1}",
                         label=f"Q_{i + 1}{i + 1}, input {i + 1} ({name})")  # fmt: skip
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        axp.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    axp.set(xlabel="frequency [Hz]", ylabel="phase of Q [deg]" if d.n_inputs == 1 else "phase of Q_ii [deg]")
    axp.set_xlim(f[0], 0.5e9 / d.period_ns)
    axp.grid(True, which="both", alpha=0.3)
    return _save(fig, out_dir / "dob_filter.png", plt)


def _locus(a: DesignAnalysis, out_dir: Path, plt: Any) -> Path:
    d = a.result.design
    dob = a.result.dob
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.plot(a.locus_gain, a.locus_magnitudes, color="0.6", lw=0.8)
    ax.plot([], [], color="0.6", lw=0.8, label="every eigenvalue magnitude")
    ax.plot(a.locus_gain, a.locus_magnitudes.max(axis=1), "b-", label="spectral radius")
    ax.axhline(1.0, color="r", lw=0.8, label="stability limit")
    ax.axvline(dob.gain, color="g", ls="--", label=f"design k = {dob.gain:.4g}")
    ax.axvline(dob.k_min_radius, color="m", ls=":", label=f"fastest k = {dob.k_min_radius:.4g}")
    unit = "DOB loop DC gain" if dob.direction_kind == "pinv(H(1))" else "scale of Kdist Lc"
    ax.set(
        xlabel=f"k [-] ({unit}; Kdist Lc = k {dob.direction_kind})",
        ylabel="|eig(Phi - Phi Lc C - Gam Kdist Lc C)| [-]",
        title=f"{d.name}: DOB gain locus",
    )
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # outside the data
    return _save(fig, out_dir / "dob_locus.png", plt)


def _ltr(a: DesignAnalysis, out_dir: Path, plt: Any) -> Path:
    d = a.result.design
    f = a.frequency_hz
    fig, ax = plt.subplots(figsize=(8, 5))
    ax.semilogx(f, _db(max_singular_value(a.ltr.Gtl)), "k-", lw=2.0, label="target Gtl (eq. 8)")
    if d.n_outputs > 1:  # the weak direction, where MIMO recovery is decided (ltr: Gtl^-1 error)
        ax.semilogx(f, _db(min_singular_value(a.ltr.Gtl)), "k:", lw=2.0, label="target Gtl, sigma_min")
    cmap = plt.get_cmap("viridis")
    q_rows = [r for r in a.ltr.rows if r.q is not None]
    for i, row in enumerate(q_rows):
        color = cmap(i / max(1, len(q_rows) - 1))
        mark = " (recovered)" if row.recovered else ""
        ax.semilogx(
            f, _db(max_singular_value(row.Lo)), "-", color=color, lw=1.0, label=f"Lo, {row.label}{mark}"
        )
    for row in a.ltr.rows:
        if row.q is None:
            ax.semilogx(f, _db(max_singular_value(row.Lo)), "r--", lw=1.5, label="Lo, design Kc")
    lo, hi = a.ltr.band_hz
    ax.axvspan(lo, hi, color="0.9", zorder=0, label="error band")
    ax.set(
        xlabel="frequency [Hz]",
        ylabel="sigma_max of the loop at the plant output [dB]"
        if d.n_outputs == 1
        else "singular value [dB]",
        title=f"{d.name}: loop transfer recovery (Lo = P K, DOB off)",
    )
    ax.set_xlim(f[0], 0.5e9 / d.period_ns)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # outside the data
    return _save(fig, out_dir / "ltr.png", plt)


def write_plots(a: DesignAnalysis, out_dir: Path) -> list[Path]:
    """Write the design PNGs into ``out_dir`` and return their paths."""
    plt = _pyplot()
    out_dir.mkdir(parents=True, exist_ok=True)
    d = a.result.design
    tag = " (sigma_max)" if d.n_outputs > 1 or d.n_inputs > 1 else ""
    return [
        _sensitivity(a, out_dir, plt, tag),
        _disturbance(a, out_dir, plt, tag),
        _dob_filter(a, out_dir, plt, tag),
        _locus(a, out_dir, plt),
        _ltr(a, out_dir, plt),
    ]


def write_tradeoff_plot(config: Config, result: DesignResult, out_dir: Path) -> Path:
    """``tradeoff.png``: the optimisation repeated over a range of noise bounds (rejection vs noise)."""
    from dob_hil.design.optimize import tradeoff_curve

    o = result.optimized
    assert o is not None
    d = result.design
    points = tradeoff_curve(config, o, d.Phi, d.Gam, d.Gam_w, d.C)
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    if points:
        ax.plot([p.noise_rms_A for p in points], [p.worst_rejection for p in points], "bo-",
                label=f"optimum per noise bound (tune {o.tune})")  # fmt: skip
    ax.plot(
        [float(np.max(o.start.noise_rms_A))], [o.start.worst_rejection], "ks", label="start (config's gains)"
    )
    ax.plot([float(np.max(o.merit.noise_rms_A))], [o.merit.worst_rejection], "r*", ms=12, label="this design")
    lo, hi = o.band_hz
    ax.set(
        xlabel="RMS noise to current [A per count RMS of encoder noise]",
        ylabel=f"worst |y / w| over {lo:g}-{hi:g} Hz [{d.output_unit} per {d.input_unit}]",
        title=f"{d.name}: disturbance rejection against current noise",
    )
    ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # outside the data
    out_dir.mkdir(parents=True, exist_ok=True)
    return _save(fig, out_dir / "tradeoff.png", plt)
