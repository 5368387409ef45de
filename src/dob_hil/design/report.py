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


def _loop(title: str, loop: dict[str, Any]) -> list[str]:
    ps, pt = loop["peak_sensitivity"], loop["peak_complementary_sensitivity"]
    dist = loop["disturbance_to_output"]
    disk = loop["disk_margin_bounds_from_peak_S"]
    lines = [f"  {title}:"]
    lines += _margins("plant input ", loop["margins_plant_input"])
    lines += _margins("plant output", loop["margins_plant_output"])
    lines.append(
        f"    peak |S| {ps['value']:.3f} ({ps['dB']:.2f} dB) at {ps['at_Hz']:.1f} Hz; "
        f"peak |T| {pt['value']:.3f} ({pt['dB']:.2f} dB) at {pt['at_Hz']:.1f} Hz"
    )
    lines.append(
        f"    from peak |S|: GM >= {_num(disk['gain_margin_dB'], '.2f', ' dB')}, "
        f"PM >= {disk['phase_margin_deg']:.1f} deg"
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
        f"  method {dob['method']}; Kdist Lc = k * D with D = {dob['direction_kind']} = "
        f"{_inline(dob['direction'])}, k = {dob['gain']:.5g}",
        f"  stable for 0 <= k < {_num(dob['stable_gain_limit'], '.5g')}; "
        f"fastest at k = {dob['min_radius_gain']:.5g} "
        f"(rho = {dob['min_radius']:.4f})",
        f"  H(1) = C (I - Phi + Phi Lc C)^-1 Gam = {_inline(dob['H1'])}",
        f"  DOB loop DC gain Kdist Lc H(1) = {_inline(dob['dc_loop_gain'])}",
        f"  DC disturbance estimate (-u_dist per unit w) = {_inline(dob['dc_disturbance_estimate_gain'], 4)}",
        "",
        "loop analysis (S, T at the plant output):",
    ]
    lines += _loop("DOB on", r["loop_dob_on"])
    lines += _loop("DOB off", r["loop_dob_off"])
    lines += ["", f"loop transfer recovery: {r['ltr']['target']}"]
    lines.append(
        f"  {'Kc from':>12s}  {'rho(Phi-Gam Kc)':>15s}  {'max rel err':>11s}  {'max wtd err':>11s}  "
        f"{'err at cross':>12s}  recovered to"
    )
    for row in r["ltr"]["rows"]:
        rec = "-" if row["recovered_to_Hz"] is None else f"{row['recovered_to_Hz']:.1f} Hz"
        lines.append(
            f"  {row['label']:>12s}  {row['feedback_radius']:15.4f}  {row['max_relative_error']:11.3g}  "
            f"{row['max_weighted_error']:11.3g}  {_num(row['relative_error_at_crossover'], '12.3g')}  {rec}"
        )
    if r.get("files"):
        lines += ["", "files:"] + [f"  {p}" for p in r["files"]]
    return "\n".join(lines)
