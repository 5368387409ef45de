"""The readable text form of the ``dob-hil design`` report (the JSON form is ``analysis.report_dict``)."""

from __future__ import annotations

from typing import Any

import numpy as np


def _mat(name: str, value: list[list[float]], indent: str = "  ") -> list[str]:
    arr = np.array(value, dtype=np.float64)
    body = np.array2string(arr, precision=6, separator=", ", max_line_width=120, floatmode="maxprec_equal")
    lines = body.splitlines()
    pad = " " * (len(name) + 3)
    return [f"{indent}{name} = {lines[0]}"] + [f"{indent}{pad}{ln}" for ln in lines[1:]]


def _inline(value: object, precision: int = 5) -> str:
    """A matrix on one line: [[a, b], [c, d]]."""
    arr = np.array(value, dtype=np.float64)
    big = float(np.max(np.abs(arr[np.isfinite(arr)]), initial=0.0))
    arr = np.where(np.abs(arr) <= 1e-12 * big, 0.0, arr)  # rounding residue: 0, not -0.
    return np.array2string(
        arr, precision=precision, separator=", ", max_line_width=10**6, suppress_small=True
    ).replace("\n", "")


def _num(v: float | None, fmt: str = ".4g", unit: str = "") -> str:
    return "none" if v is None else f"{v:{fmt}}{unit}"


def _margins(label: str, items: list[dict[str, Any]]) -> list[str]:
    out = []
    for i, m in enumerate(items):
        gm = _num(m["gain_margin_dB"], ".2f", " dB")
        gm_at = _num(m["gain_margin_at_Hz"], ".1f", " Hz")
        pm = _num(m["phase_margin_deg"], ".1f", " deg")
        pm_at = _num(m["phase_margin_at_Hz"], ".1f", " Hz")
        out.append(f"    {label}[{i}]: GM {gm} at {gm_at}, PM {pm} at {pm_at}")
    return out


def _gm(dm: dict[str, Any]) -> str:
    """A balanced disk gain margin: +/-x dB, or inf (alpha >= 2, null in the JSON)."""
    return "+/-inf dB" if dm["gain_margin_dB"] is None else f"+/-{dm['gain_margin_dB']:.2f} dB"


def _channel(kind: str, i: int, names: list[str]) -> str:
    """``input 1 (i1)``: channels counted from 1, with the config's name where it says more."""
    label = f"{kind} {i + 1}"
    return f"{label} ({names[i]})" if i < len(names) and names[i] not in ("", label) else label


def _loop_mimo(title: str, loop: dict[str, Any], names: tuple[list[str], list[str]]) -> list[str]:
    """A loop's figures for a plant with several inputs or outputs: one table row per channel (loop
    at a time), the multiloop disk margins, and noise to current per input."""
    ins, outs = names
    ps, pt = loop["peak_sensitivity"], loop["peak_complementary_sensitivity"]
    lines = [
        f"  {title}:",
        "    loop at a time (that channel broken, every other loop closed):",
        f"      {'channel':18s} {'gain margin':>21s} {'phase margin':>21s} {'disk gain':>11s} "
        f"{'disk phase':>12s} {'alpha':>6s} {'disk min at':>11s} {'delay margin':>22s}",
    ]
    rows = []
    for kind in ("input", "output"):
        pairs = zip(loop[f"margins_plant_{kind}"], loop[f"disk_margins_plant_{kind}"], strict=True)
        rows += [(kind, i, m, d) for i, (m, d) in enumerate(pairs)]
    for kind, i, m, d in rows:
        gm = f"{_num(m['gain_margin_dB'], '.2f', ' dB')} at {_num(m['gain_margin_at_Hz'], '.1f', ' Hz')}"
        pm = f"{_num(m['phase_margin_deg'], '.1f', ' deg')} at {_num(m['phase_margin_at_Hz'], '.1f', ' Hz')}"
        delay = "-"
        if kind == "input":
            dm = loop["delay_margin_per_input"][i]
            delay = "none" if dm["s"] is None else f"{dm['s'] * 1e6:.0f} us = {dm['samples']:.2f} samples"
        names_ = ins if kind == "input" else outs
        lines.append(
            f"      {_channel(kind, i, names_):18s} {gm:>21s} {pm:>21s} {_gm(d):>11s} "
            f"{'+/-' + format(d['phase_margin_deg'], '.1f') + ' deg':>12s} {d['alpha']:6.3f} "
            f"{d['at_Hz']:8.1f} Hz {delay:>22s}"
        )
    for key in ("multiloop_disk_margin_plant_input", "multiloop_disk_margin_plant_output"):
        mm = loop[key]
        lo, hi = mm["alpha"], mm["alpha_upper_bound"]
        bounds = "mu bounds agree" if hi - lo <= 1e-6 * lo else f"alpha_max <= {hi:.3f}"
        lines.append(
            f"    multiloop disk margin at the {mm['where']} (every channel perturbed at once): "
            f"{_gm(mm)}, +/-{mm['phase_margin_deg']:.1f} deg "
            f"(alpha {lo:.3f}, {bounds}; at {mm['at_Hz']:.1f} Hz)"
        )
    lines.append(
        f"    peak sigma_max(S) {ps['value']:.3f} ({ps['dB']:.2f} dB) at {ps['at_Hz']:.1f} Hz; "
        f"peak sigma_max(T) {pt['value']:.3f} ({pt['dB']:.2f} dB) at {pt['at_Hz']:.1f} Hz"
    )
    nz = loop["noise_to_current"]
    lines.append("    noise to current (one encoder count; RMS: white, 1 count RMS on every output; "
                 "peak: worst direction):")  # fmt: skip
    for i, (rms, pk, at) in enumerate(
        zip(
            nz["rms_A_per_count_rms"],
            nz["peak_A_per_count_per_input"],
            nz["peak_at_Hz_per_input"],
            strict=True,
        )
    ):
        lines.append(f"      {_channel('input', i, ins):18s} RMS {rms:.4g} A, peak {pk:.4g} A at {at:.0f} Hz")
    lines.append(f"      {'all inputs':18s} peak sigma_max(K S) {nz['peak_A_per_count']:.4g} A at "
                 f"{nz['peak_at_Hz']:.0f} Hz")  # fmt: skip
    dist = loop["disturbance_to_output"]
    pk = dist["peak"]
    lines.append(
        f"    w -> y: peak sigma_max {pk['value']:.4g} at {pk['at_Hz']:.3g} Hz, at the lowest grid "
        f"frequency {dist['lowest_grid_frequency_gain']:.4g}"
    )
    for item in dist["at_configured_disturbances"]:
        per = ", ".join(
            f"{_channel('output', j, outs)} {g:.4g}" for j, g in enumerate(item["gain_per_output"])
        )
        lines.append(
            f"    w -> y at {item['frequency_Hz']:g} Hz (configured disturbance on "
            f"{_channel('input', item['input_index'], ins)}): ||y / w|| {item['gain']:.4g}; {per}"
        )
    return lines


def _loop(title: str, loop: dict[str, Any]) -> list[str]:
    ps, pt = loop["peak_sensitivity"], loop["peak_complementary_sensitivity"]
    dist = loop["disturbance_to_output"]
    lines = [f"  {title}:"]
    lines += _margins("plant input ", loop["margins_plant_input"])
    lines += _margins("plant output", loop["margins_plant_output"])
    lines.append(
        f"    peak |S| {ps['value']:.3f} ({ps['dB']:.2f} dB) at {ps['at_Hz']:.1f} Hz; "
        f"peak |T| {pt['value']:.3f} ({pt['dB']:.2f} dB) at {pt['at_Hz']:.1f} Hz"
    )
    for where, key in (
        ("plant input ", "disk_margins_plant_input"),
        ("plant output", "disk_margins_plant_output"),
    ):
        for i, dm in enumerate(loop[key]):
            lines.append(
                f"    disk margin (balanced) {where}[{i}]: {_gm(dm)}, "
                f"+/-{dm['phase_margin_deg']:.1f} deg (alpha {dm['alpha']:.3f}, at {dm['at_Hz']:.1f} Hz)"
            )
    dm = loop["delay_margin"]
    lines.append(
        "    delay margin: "
        + (
            "none (no gain crossover)"
            if dm["s"] is None
            else f"{dm['s'] * 1e6:.0f} us = {dm['samples']:.2f} samples"
        )
    )
    nz = loop["noise_to_current"]
    lines.append(
        "    noise to current (one encoder count): RMS "
        + ", ".join(f"{v:.4g}" for v in nz["rms_A_per_count_rms"])
        + f" A (white, 1 count RMS), peak {nz['peak_A_per_count']:.4g} A at {nz['peak_at_Hz']:.0f} Hz"
    )
    pk = dist["peak"]
    lines.append(
        f"    w -> y: peak {pk['value']:.4g} at {pk['at_Hz']:.2f} Hz, at the lowest grid frequency "
        f"{dist['lowest_grid_frequency_gain']:.4g}"
    )
    for item in dist["at_configured_disturbances"]:
        lines.append(
            f"    w -> y at {item['frequency_Hz']:g} Hz (configured disturbance): {item['gain']:.4g}"
        )
    return lines


def format_report(r: dict[str, Any]) -> str:
    """Multi-line text report of :func:`dob_hil.design.analysis.report_dict` output."""
    lines = [
        f"design {r['name']}: Ts = {r['period_ns'] / 1000:g} us (Nyquist {r['nyquist_Hz']:.1f} Hz), "
        f"{r['n_plant_states']} plant states, input delay {r['input_delay_samples']} sample(s)",
        f"  augmented states: {', '.join(r['state_names'])}",
        "",
        "discrete plant (ZOH):",
    ]
    for key in ("Phi", "Gam", "C"):
        lines += _mat(key, r[key])
    lines += ["", "gains:"]
    for key in ("Lc", "Kc", "Kdist", "Kdist_Lc"):
        lines += _mat(key.replace("_", " "), r[key])
    for key, src in r["gain_sources"].items():
        lines.append(f"  {key}: {src}")
    for key, sol in r["riccati"].items():
        if sol is not None:
            lines.append(f"  {key} DARE relative residual: {sol['relative_residual']:.2e}")
    lines += ["", "Theorem 1 (eigenvalue magnitudes):"]
    for key, mags in r["spectral_radii"].items():
        rho = max(mags)
        flag = "stable" if rho < 1 else "UNSTABLE"
        if key == "dob" and not r["dob_enabled"]:
            flag += " (DOB disabled: not required)"
        lines.append(
            f"  {key:9s} rho({r['matrices'][key]}) = {', '.join(f'{v:.4f}' for v in mags)}  [{flag}]"
        )
    dob = r["dob"]
    lines += [
        "",
        "disturbance observer:",
        f"  method {dob['method']}: {dob['method_aim']}",
        f"  Kdist Lc = k * D with D = {dob['direction_kind']} = "
        f"{_inline(dob['direction'])}, k = {dob['gain']:.5g}",
        f"  stable for 0 <= k < {_num(dob['stable_gain_limit'], '.5g')}; "
        f"fastest at k = {dob['min_radius_gain']:.5g} "
        f"(rho = {dob['min_radius']:.4f})",
        f"  H(1) = C (I - Phi + Phi Lc C)^-1 Gam = {_inline(dob['H1'])}",
        f"  DOB loop DC gain Kdist Lc H(1) = {_inline(dob['dc_loop_gain'])}",
        f"  DC disturbance estimate (-u_dist per unit w) = {_inline(dob['dc_disturbance_estimate_gain'], 4)}",
        "  disturbance-to-estimate filter Q(z) = Kdist Lc C (zI - Phi + Phi Lc C + Gam Kdist Lc C)^-1 Gam_w:",
        f"    Q(1) = {_inline(r['disturbance_estimate_filter']['Q1'], 4)}, peak "
        f"{r['disturbance_estimate_filter']['peak']:.4g}, -3 dB at "
        f"{_num(r['disturbance_estimate_filter']['bandwidth_Hz'], '.1f', ' Hz')} (Q is not T)",
        "",
        "poles (closed loop = feedback and DOB matrices, Theorem 1):",
    ]
    if not r["pole_flags"]:
        lines.append("  no negative real (|z| >= 0.3) or lightly damped (zeta < 0.1) pole")
    for pf in r["pole_flags"]:
        re, im = pf["eigenvalue"]
        lines.append(
            f"  {pf['kind']}: z = {re:.4f}{im:+.4f}j (|z| {pf['magnitude']:.4f}, "
            f"zeta {pf['damping_ratio']:.3f}) of {pf['matrix']}"
            + (" -- alternates sign each sample: command chatter" if pf["kind"] == "negative real" else "")
        )
    lines += ["", "loop analysis (S, T at the plant output):"]
    on = r["loop_dob_on"]
    mimo = len(on["margins_plant_input"]) > 1 or len(on["margins_plant_output"]) > 1
    names = (list(r.get("input_names", [])), list(r.get("output_names", [])))
    for title, key in (("DOB on", "loop_dob_on"), ("DOB off", "loop_dob_off")):
        lines += _loop_mimo(title, r[key], names) if mimo else _loop(title, r[key])
    ltr = r["ltr"]
    lo, hi = ltr["band_Hz"]
    lines += ["", f"loop transfer recovery: {ltr['target']}"]
    lines.append(
        f"  error = {ltr.get('error', 'sigma_max(Lo_q - Gtl) / sigma_max(Gtl)')}; band {lo:.3g}-{hi:.3g} Hz "
        "(design.feedback.ltr_band_hz); recovered = band error <= 10 %"
    )
    lines.append(
        f"  {'Kc from':>12s}  {'rho(Phi-Gam Kc)':>15s}  {'band err':>9s}  {'max rel err':>11s}  "
        f"{'max wtd err':>11s}  {'err at cross':>12s}  10 % up to"
    )
    for row in ltr["rows"]:
        rec = "-" if row["recovered_to_Hz"] is None else f"{row['recovered_to_Hz']:.1f} Hz"
        mark = " recovered" if row["recovered_in_band"] else ""
        lines.append(
            f"  {row['label']:>12s}  {row['feedback_radius']:15.4f}  {row['band_relative_error']:9.3g}  "
            f"{row['max_relative_error']:11.3g}  {row['max_weighted_error']:11.3g}  "
            f"{_num(row['relative_error_at_crossover'], '12.3g')}  {rec}{mark}"
        )
    if ltr["recovered_at_q"] is not None:
        lines.append(f"  recovered in the band from q = {ltr['recovered_at_q']:g}")
    for note in ltr["obstructions"]:
        lines.append(f"  cannot recover: {note}")
    for note in ltr["notes"]:
        lines.append(f"  note: {note}")
    opt = r.get("optimize")
    if opt is not None:
        lines += [
            "",
            f"optimize (tune {opt['tune']}, band {opt['band_Hz'][0]:g}-{opt['band_Hz'][1]:g} Hz, "
            f"{opt['solver']}):",
        ]
        lines.append(f"  {'':24s} {'start':>10s} {'result':>10s}   bound")
        b = opt["bounds"]
        rows_ = [
            ("worst |y/w| in band", "worst_rejection", None),
            ("peak |S|", "peak_S", b["max_peak_S"]),
            ("peak |T|", "peak_T", b["max_peak_T"]),
            ("noise RMS [A/count]", "noise_rms_A", b["max_noise_rms_A"]),
            ("noise peak [A/count]", "noise_peak_A", b["max_noise_peak_A"]),
            ("gain margin [dB]", "gain_margin_dB", b["min_gain_margin_dB"]),
            ("phase margin [deg]", "phase_margin_deg", b["min_phase_margin_deg"]),
            ("disk gain margin [dB]", "disk_gain_margin_dB", b["min_disk_gain_margin_dB"]),
            ("disk phase margin [deg]", "disk_phase_margin_deg", b["min_disk_phase_margin_deg"]),
            ("delay margin [us]", "delay_margin_s", b["min_delay_margin_samples"]),
        ]
        for label, key, bound in rows_:
            a0, a1 = opt["start"][key], opt["result"][key]
            if key == "noise_rms_A":
                a0, a1 = max(a0), max(a1)
            scale = 1e6 if key == "delay_margin_s" else 1.0
            bound_s = (
                "-"
                if bound is None
                else (f"{bound:g} samples" if key == "delay_margin_s" else f"{bound:.4g}")
            )
            lines.append(f"  {label:24s} {_num(None if a0 is None else a0 * scale, '10.4g')} "
                         f"{_num(None if a1 is None else a1 * scale, '10.4g')}   {bound_s}")  # fmt: skip
        lines.append(f"  rejection {opt['rejection_gain']:.2f}x the start's over the band")
    if r.get("warnings"):
        lines += ["", "WARNINGS:"] + [f"  {w}" for w in r["warnings"]]
    if r.get("files"):
        lines += ["", "files:"] + [f"  {p}" for p in r["files"]]
    return "\n".join(lines)


def gains_toml(result: Any) -> str:
    """The optimised gains as TOML tables to paste into a config (explicit gains)."""

    def rows(M: Any) -> str:
        arr = np.asarray(M, dtype=np.float64)
        return "[" + ", ".join("[" + ", ".join(f"{v:.8g}" for v in row) + "]" for row in arr) + "]"

    o = result.optimized
    lines = [f"# found by dob-hil design --optimize: {o.summary}"]
    if o.tune == "all":
        lines += [
            "[design.estimator]",
            f"Lc = {rows(o.Lc)}",
            "",
            "[design.feedback]",
            f"Kc = {rows(o.Kc)}",
            "",
        ]
    lines += ["[design.dob]", f"Kdist = {rows(o.Kdist)}"]
    return "\n".join(lines)
