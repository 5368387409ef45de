"""``dob-hil campaign FILE``: run a robustness campaign (or ``--rerun CASE_ID`` one of its cases).

Writes into ``--out`` (default ``logs/campaign-<name>/``): ``journal.jsonl`` (resume),
``results.parquet`` (one row per case), ``logs/`` (the worst cases' and failures' MCAPs),
``report.md`` and PNG plots.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from dob_hil.errors import ConfigError


def _runner(args: argparse.Namespace) -> Any:
    from dob_hil.campaign.run import Runner
    from dob_hil.campaign.runners import default_workers

    if args.scheduler and args.local_cluster:
        raise ConfigError("--scheduler", "give --scheduler ADDRESS or --local-cluster, not both")
    if args.workers is not None and not 1 <= args.workers <= 4096:
        raise ConfigError("--workers", f"must be 1..4096, got {args.workers}")
    workers = args.workers or default_workers()
    if args.scheduler or args.local_cluster:
        try:
            import distributed  # noqa: F401
        except ImportError:
            raise ConfigError(
                "--scheduler", "Dask is not installed: pip install 'dob-hil[campaign]'"
            ) from None
        return Runner("dask", workers, args.scheduler)
    return Runner("serial" if workers == 1 else "pool", workers)


def _clean(v: Any) -> Any:
    """NaN -> None, recursively: strict JSON."""
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_clean(x) for x in v]
    return None if isinstance(v, float) and not math.isfinite(v) else v


def _rerun(spec: Any, out: Path, case_id: str, as_json: bool) -> int:
    from dob_hil.campaign.execute import run_case
    from dob_hil.campaign.run import find_case
    from dob_hil.campaign.table import read_table

    case = find_case(spec, case_id)
    row = run_case(spec, case, out / "rerun", keep_log=True)
    table = out / "results.parquet"
    verdict = "no results table to compare with"
    if table.exists():
        old = next((r for r in read_table(table) if r["case_id"] == case_id), None)
        if old is not None:
            same = all(
                (old.get(k) == v) or (isinstance(v, float) and math.isnan(v) and math.isnan(old.get(k, 0.0)))
                for k, v in row.items()
                if k not in ("wall_s", "log")
            )
            verdict = "identical to the table's row" if same else "DIFFERENT from the table's row"
    if as_json:
        print(json.dumps(_clean({"row": row, "verdict": verdict}), indent=1, allow_nan=False))
    else:
        params = ", ".join(f"{k[6:]}={v:.6g}" if isinstance(v, float) else f"{k[6:]}={v}"
                           for k, v in row.items() if k.startswith("param."))  # fmt: skip
        print(f"case {case_id} (seed {row['seed']}): {row['exit_reason']}; {params}")
        print(f"  tracking error rms {row['tracking_error_rms']:.6g}, max {row['tracking_error_max']:.6g}")
        print(f"  log {row['log']}; metrics {verdict}")
    return 0


def main(args: argparse.Namespace) -> int:
    from dob_hil.campaign.report import summarize, write_report
    from dob_hil.campaign.run import run_campaign
    from dob_hil.campaign.spec import load_campaign
    from dob_hil.commands.paths import ensure_dir

    spec = load_campaign(args.file)
    out = Path(args.out) if args.out else Path("logs") / f"campaign-{spec.name}"
    ensure_dir(out, "--out")
    if args.rerun:
        return _rerun(spec, out, args.rerun, args.json)
    runner = _runner(args)
    from dob_hil.commands.progress import ProgressBar

    bar = ProgressBar(f"campaign {spec.name}", not args.no_progress and not args.json)
    try:
        result = run_campaign(spec, out, runner, progress=bar if bar.enabled else None)
    finally:
        bar.finish()
    summary = summarize(spec, result.rows)
    written = write_report(spec, result.rows, out, summary) if not args.no_report else []
    info = {
        "campaign": spec.name,
        "cases": len(result.rows),
        "resumed": result.resumed,
        "ran": result.ran,
        "batches": result.batches,
        "runner": runner.kind,
        "workers": runner.workers,
        "table": str(result.table_path),
        "kept_logs": result.kept_logs,
        "report": [str(p) for p in written],
        "summary": summary,
    }
    if args.json:
        print(json.dumps(_clean(info), indent=1, allow_nan=False))
    else:
        print(f"campaign {spec.name}: {len(result.rows)} cases ({result.resumed} from the journal, "
              f"{result.ran} run in {result.batches} batches, "
              f"{runner.kind}, {runner.workers} workers)")  # fmt: skip
        for group in summary["groups"]:
            print(f"  {group['label']:<8} {group['cases']} cases: stable {group['stable_fraction']:.1%}, "
                  f"within {spec.tracking_bound:g} {group['within_fraction']:.1%}, median "
                  f"{spec.metric} {group['median']:.4g}")  # fmt: skip
        print(f"  table {result.table_path}; {len(result.kept_logs)} logs kept; report {out / 'report.md'}")
    return 0
