"""Where the batches run: in this process, on a local process pool, or on Dask distributed.

Each runner yields the rows of a batch as it finishes (any order); the caller journals them and
sorts the table by case index, so the order of completion never shows in the results.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import TYPE_CHECKING, Any

from dob_hil.campaign.execute import run_batch

if TYPE_CHECKING:
    from dob_hil.campaign.cases import Case
    from dob_hil.campaign.spec import CampaignSpec

Rows = list[dict[str, Any]]


def default_workers() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def batches(cases: list[Case], workers: int, batch_size: int) -> list[list[Case]]:
    """``batch_size`` cases per task; 0: about four tasks per worker, at most 20 cases each
    (a task's overhead against its work: BENCHMARKS.md, "Campaigns")."""
    if batch_size <= 0:
        batch_size = max(1, min(20, -(-len(cases) // (4 * max(1, workers)))))
    return [cases[i : i + batch_size] for i in range(0, len(cases), batch_size)]


def run_serial(spec: CampaignSpec, work: list[list[Case]], keep_dir: str | None) -> Iterator[Rows]:
    for batch in work:
        yield run_batch(spec, batch, keep_dir)


def run_pool(
    spec: CampaignSpec, work: list[list[Case]], keep_dir: str | None, workers: int
) -> Iterator[Rows]:
    # spawn: fresh workers, whatever threads this process has (Dask's, a progress bar's)
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
        futures = [pool.submit(run_batch, spec, batch, keep_dir) for batch in work]
        try:
            for fut in as_completed(futures):
                yield fut.result()
        finally:
            for fut in futures:
                fut.cancel()


def run_dask(
    spec: CampaignSpec,
    work: list[list[Case]],
    keep_dir: str | None,
    *,
    scheduler: str | None,
    workers: int,
) -> Iterator[Rows]:
    """On an existing cluster (``scheduler``: its address) or a LocalCluster of ``workers``
    single-threaded processes. Dask schedules; one task per batch."""
    from importlib import import_module

    dd: Any = import_module("distributed")  # untyped: one Any at the boundary
    Client, LocalCluster, dask_completed = dd.Client, dd.LocalCluster, dd.as_completed

    cluster = None
    if scheduler is None:
        cluster = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None
        )
        client = Client(cluster)
    else:
        client = Client(scheduler)
    try:
        n = len(work)  # map's iterables are the positional arguments
        futures = client.map(run_batch, [spec] * n, work, [keep_dir] * n, pure=False)
        try:
            for fut in dask_completed(futures):
                yield fut.result()
        finally:
            client.cancel(futures)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
