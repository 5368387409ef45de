"""The campaign's report: a summary (per DOB on/off: stable and within-bound fractions, metric
percentiles), the worst cases, and PNGs: the metric's distributions DOB on against off and the
robustness maps (the metric against each varied number, and against the first two together)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from dob_hil.campaign.spec import CampaignSpec


def _groups(rows: list[dict[str, Any]]) -> list[tuple[str, list[dict[str, Any]]]]:
    flags = sorted({r.get("dob_enabled") for r in rows}, key=lambda f: (f is None, not f))
    label = {True: "DOB on", False: "DOB off", None: "all"}
    return [(label[f], [r for r in rows if r.get("dob_enabled") == f]) for f in flags]


def _values(rows: list[dict[str, Any]], key: str) -> np.ndarray[Any, np.dtype[np.float64]]:
    v = np.array([r.get(key, math.nan) for r in rows], dtype=np.float64)
    return v[np.isfinite(v)]


def summarize(spec: CampaignSpec, rows: list[dict[str, Any]]) -> dict[str, Any]:
    groups = []
    for label, rs in _groups(rows):
        v = _values(rs, spec.metric)
        n = len(rs)
        groups.append({
            "label": label,
            "cases": n,
            "completed": sum(r["exit_reason"] == "completed" for r in rs),
            "failures": sum(bool(r["error"]) or r["exit_reason"] != "completed" for r in rs),
            "stable_fraction": sum(bool(r["stable"]) for r in rs) / n if n else math.nan,
            "within_fraction": sum(bool(r["within_bound"]) for r in rs) / n if n else math.nan,
            "median": float(np.median(v)) if len(v) else math.nan,
            "p90": float(np.percentile(v, 90)) if len(v) else math.nan,
            "max": float(v.max()) if len(v) else math.nan,
        })  # fmt: skip
    out: dict[str, Any] = {"metric": spec.metric, "tracking_bound": spec.tracking_bound, "groups": groups}
    by = {g["label"]: g for g in groups}
    if "DOB on" in by and "DOB off" in by and by["DOB on"]["median"] > 0:
        out["median_ratio_off_to_on"] = by["DOB off"]["median"] / by["DOB on"]["median"]
    return out


def _numeric_params(spec: CampaignSpec) -> list[str]:
    return [v.key for v in spec.vary if v.dist != "grid" and v.key != "run.dob_enabled"
            and all(isinstance(x, int | float) and not isinstance(x, bool) for x in v.values)]  # fmt: skip


def _fmt(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def _markdown(
    spec: CampaignSpec, rows: list[dict[str, Any]], summary: dict[str, Any], pngs: list[Path]
) -> str:
    from dob_hil.campaign.run import worst_cases

    m = spec.metric
    lines = [
        f"# Campaign {spec.name}",
        "",
        f"{len(rows)} cases ({spec.samples} draws, seed {spec.seed}), "
        f"base `{Path(spec.base_source).name}`, "
        f"{spec.duration_s:g} s per case, metrics from {spec.from_s:g} s. Stable: completed with "
        f"tracking_error_max <= {spec.stable_bound:g}; "
        f"within bound: tracking_error_max <= {spec.tracking_bound:g}.",
        "",
        f"| group | cases | failures | stable | within bound | median {m} | p90 | max |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for g in summary["groups"]:
        lines.append(
            f"| {g['label']} | {g['cases']} | {g['failures']} | {g['stable_fraction']:.1%} | "
            f"{g['within_fraction']:.1%} | {g['median']:.4g} | {g['p90']:.4g} | {g['max']:.4g} |"
        )
    if "median_ratio_off_to_on" in summary:
        ratio = summary["median_ratio_off_to_on"]
        lines += ["", f"Median {m}, DOB off / DOB on: {ratio:.2f}x."]
    params = [v.key for v in spec.vary]
    lines += ["", f"## Worst {spec.keep_worst} cases by {m} (logs kept; rerun: `--rerun CASE_ID`)",
              "", "| case | " + " | ".join(params) + f" | {m} | exit |",
              "|---|" + "---:|" * len(params) + "---:|---|"]  # fmt: skip
    for r in worst_cases(spec, rows, spec.keep_worst):
        cells = " | ".join(_fmt(r.get(f"param.{k}")) for k in params)
        lines.append(f"| {r['case_id']} | {cells} | {_fmt(r.get(m))} | {r['exit_reason']} |")
    failures = [r for r in rows if r["exit_reason"] != "completed" or r["error"]]
    if failures:
        lines += ["", f"## Failures ({len(failures)})", ""]
        lines += [f"- {r['case_id']}: {r['exit_reason']} {r['error']}".rstrip() for r in failures[:50]]
    lines += ["", *[f"![{p.stem}]({p.name})" for p in pngs]]
    return "\n".join(lines) + "\n"


def write_report(
    spec: CampaignSpec, rows: list[dict[str, Any]], out: Path, summary: dict[str, Any]
) -> list[Path]:
    """report.md, summary table, distributions.png, map-*.png in ``out``; the paths written."""
    import json

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    m = spec.metric
    groups = _groups(rows)
    pngs: list[Path] = []
    all_v = _values(rows, m)
    positive = all_v[all_v > 0]
    if len(positive):
        lo, hi = float(positive.min()), float(positive.max())
        bins = np.geomspace(lo, hi * 1.0001 if hi > lo else lo * 2, 40)
        fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
        for label, rs in groups:
            v = _values(rs, m)
            v = v[v > 0]
            ax1.hist(v, bins=bins, alpha=0.55, label=f"{label} (median {np.median(v):.3g})")
            ax2.plot(np.sort(v), np.arange(1, len(v) + 1) / len(v), label=label)
        for ax in (ax1, ax2):
            ax.set_xscale("log")
            ax.set_xlabel(m)
            ax.grid(True, which="both", alpha=0.3)
        ax1.set_ylabel("cases")
        ax2.set_ylabel("fraction of cases <=")
        if m == "tracking_error_max":
            ax2.axvline(spec.tracking_bound, color="k", ls="--", label="tracking bound")
        ax1.legend()
        ax2.legend()
        fig.suptitle(f"{spec.name}: {len(rows)} cases")
        fig.tight_layout()
        pngs.append(out / "distributions.png")
        fig.savefig(pngs[-1], dpi=110)
        plt.close(fig)
    numeric = _numeric_params(spec)
    norm = LogNorm(vmin=float(positive.min()), vmax=float(positive.max())) if len(positive) else None
    if numeric and norm is not None:
        fig, axes = plt.subplots(len(groups), len(numeric), figsize=(3.6 * len(numeric), 3.2 * len(groups)),
                                 squeeze=False)  # fmt: skip
        for gi, (label, rs) in enumerate(groups):
            for pi, key in enumerate(numeric):
                ax = axes[gi][pi]
                x = np.array([r.get(f"param.{key}") for r in rs], dtype=np.float64)
                y = np.array([r.get(m) for r in rs], dtype=np.float64)
                ax.scatter(x, y, s=6, alpha=0.6)
                ax.set_yscale("log")
                ax.set_xlabel(key)
                ax.set_ylabel(f"{m} ({label})" if pi == 0 else "")
                ax.grid(True, alpha=0.3)
        fig.tight_layout()
        pngs.append(out / "map-1d.png")
        fig.savefig(pngs[-1], dpi=100)
        plt.close(fig)
    if len(numeric) >= 2 and norm is not None:
        kx, ky = numeric[-2], numeric[-1]  # the last two: the disturbance in the shipped study
        fig, axes = plt.subplots(
            1, len(groups), figsize=(5.2 * len(groups), 4.2), squeeze=False, layout="constrained"
        )
        sc = None
        for gi, (label, rs) in enumerate(groups):
            ax = axes[0][gi]
            x = np.array([r.get(f"param.{kx}") for r in rs], dtype=np.float64)
            y = np.array([r.get(f"param.{ky}") for r in rs], dtype=np.float64)
            c = np.array([r.get(m) for r in rs], dtype=np.float64)
            c = np.where(np.isfinite(c) & (c > 0), c, float(norm.vmax or 1.0))
            sc = ax.scatter(x, y, c=c, s=14, cmap="viridis", norm=norm)
            ax.set_title(label)
            ax.set_xlabel(kx)
            if gi == 0:
                ax.set_ylabel(ky)
        if sc is not None:
            fig.colorbar(sc, ax=axes[0].tolist(), label=m)
        pngs.append(out / "map-2d.png")
        fig.savefig(pngs[-1], dpi=100)
        plt.close(fig)
    (out / "summary.json").write_text(json.dumps(summary, indent=1, default=lambda v: None) + "\n")
    (out / "report.md").write_text(_markdown(spec, rows, summary, pngs), encoding="utf-8")
    return [out / "report.md", out / "summary.json", *pngs]
