"""A whole campaign: the cases not yet in the journal, in batches on the chosen runner, then
the table, the kept logs of the worst cases (re-run, so nothing else writes a log) and the report."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dob_hil.campaign.cases import Case, generate_cases
from dob_hil.campaign.execute import run_case
from dob_hil.campaign.journal import Journal
from dob_hil.campaign.runners import Rows, batches, run_dask, run_pool, run_serial
from dob_hil.campaign.spec import CampaignSpec
from dob_hil.campaign.table import write_table
from dob_hil.errors import ConfigError


@dataclass(frozen=True)
class Runner:
    kind: str  # "serial", "pool" or "dask"
    workers: int
    scheduler: str | None = None  # dask: an existing cluster's address; None: a LocalCluster


@dataclass
class CampaignResult:
    rows: list[dict[str, Any]]
    table_path: Path
    resumed: int  # cases found in the journal
    ran: int  # cases run now
    batches: int
    kept_logs: list[str]


def _rows_iter(spec: CampaignSpec, work: list[list[Case]], keep: str, runner: Runner) -> Iterator[Rows]:
    if runner.kind == "serial":
        return run_serial(spec, work, keep)
    if runner.kind == "pool":
        return run_pool(spec, work, keep, runner.workers)
    if runner.kind == "dask":
        return run_dask(spec, work, keep, scheduler=runner.scheduler, workers=runner.workers)
    raise ConfigError("runner", f"unknown kind {runner.kind!r}")


def worst_cases(spec: CampaignSpec, rows: list[dict[str, Any]], n: int) -> list[dict[str, Any]]:
    """The ``n`` rows with the largest ``spec.metric`` (NaN: a case without metrics, ranked last;
    ties by case index)."""

    def key(r: dict[str, Any]) -> tuple[float, int]:
        v = r.get(spec.metric)
        v = v if isinstance(v, float) and not math.isnan(v) else -math.inf
        return (-v, int(r["index"]))

    return sorted(rows, key=key)[:n]


def run_campaign(
    spec: CampaignSpec,
    out: Path,
    runner: Runner,
    progress: Callable[[int, int], None] | None = None,
) -> CampaignResult:
    out.mkdir(parents=True, exist_ok=True)
    logs_dir = out / "logs"
    journal = Journal(out / "journal.jsonl", spec.fingerprint, spec.name)
    cases = generate_cases(spec)
    resumed = sum(1 for c in cases if c.index in journal.rows)
    todo = [c for c in cases if c.index not in journal.rows]
    work = batches(todo, runner.workers, spec.batch_size)
    done = resumed
    if progress is not None:
        progress(done, len(cases))
    for rows in _rows_iter(spec, work, str(logs_dir), runner):
        journal.append(rows)
        done += len(rows)
        if progress is not None:
            progress(done, len(cases))
    rows = [journal.rows[c.index] for c in cases]
    table_path = out / "results.parquet"
    write_table(rows, table_path)
    kept = [r["log"] for r in rows if r.get("log")]
    by_index = {c.index: c for c in cases}
    for r in worst_cases(spec, rows, spec.keep_worst):
        path = logs_dir / f"{r['case_id']}.mcap"
        if not path.exists():
            run_case(spec, by_index[int(r["index"])], logs_dir, keep_log=True)
        kept.append(str(path))
    return CampaignResult(rows, table_path, resumed, len(todo), len(work), sorted(set(kept)))


def find_case(spec: CampaignSpec, case_id: str) -> Case:
    for case in generate_cases(spec):
        if case.case_id == case_id:
            return case
    raise ConfigError("--rerun", f"no case {case_id!r} in this campaign (c000000 .. c{spec.n_cases - 1:06d})")
