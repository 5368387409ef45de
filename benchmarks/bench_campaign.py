"""Campaign throughput: cases per minute serially, on the process pool and on Dask, in one run.

The paper's 1 s step scenario (3,333 lockstep samples, logged to a scratch MCAP, analysed, the
log deleted) with its plant gain and disturbance varied, DOB on and off. Measured in the same
run: serial cases/min, the pool's cases/min on every CPU and its parallel efficiency (pool rate
/ (workers x serial rate)), a Dask LocalCluster of as many single-threaded worker processes with
one task per worker and with one case per task (the scheduling overhead batching saves), the
cost of scheduling one empty task on each (startup excluded), and the startup of each (a pool
of fresh processes, a LocalCluster). From these, the wall time of a 100,000-case campaign on N
workers, on paper.

    .venv/bin/python benchmarks/bench_campaign.py [--smoke] [--json] [--cases N]
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path
from typing import Any

from _common import parser, report

from dob_hil.campaign.run import Runner, run_campaign
from dob_hil.campaign.runners import default_workers
from dob_hil.campaign.spec import load_campaign

SPEC = """
[campaign]
name = "bench"
base = "paper-step"
seed = 1
samples = {draws}
duration_s = {duration_s}
from_s = {from_s}
keep_worst = 0
batch_size = {batch}

[[vary]]
key = "plant.B[1]"
relative = [-0.3, 0.3]

[[vary]]
key = "sim.disturbance[0].amplitude_A"
uniform = [0.0, 0.4]

[[vary]]
key = "run.dob_enabled"
grid = [true, false]
"""


def _timed(
    folder: Path, tag: str, runner: Runner, cases: int, duration_s: float, batch: int
) -> dict[str, Any]:
    spec_path = folder / f"{tag}.toml"
    text = SPEC.format(draws=cases // 2, duration_s=duration_s, from_s=min(0.1, duration_s / 4), batch=batch)
    spec_path.write_text(text, encoding="utf-8")
    spec = load_campaign(spec_path)
    t0 = time.perf_counter()
    result = run_campaign(spec, folder / tag, runner)
    wall_s = time.perf_counter() - t0
    assert all(r["exit_reason"] == "completed" for r in result.rows)
    case_s = sum(r["wall_s"] for r in result.rows)  # inside the workers, per case
    return {
        "cases": len(result.rows),
        "batches": result.batches,
        "wall_s": wall_s,
        "cases_per_min": len(result.rows) / wall_s * 60,
        "case_s_mean": case_s / len(result.rows),
        "metrics": [r["tracking_error_rms"] for r in result.rows],
    }


def _noop(x: int) -> int:
    return x


def _per_task_overhead_ms(workers: int, tasks: int) -> dict[str, float]:
    """Scheduling cost of one task that does nothing, pool against Dask, startup excluded."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from distributed import Client, LocalCluster

    out = {}
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        list(pool.map(_noop, range(workers)))  # started
        t0 = time.perf_counter()
        for f in [pool.submit(_noop, i) for i in range(tasks)]:
            f.result()
        out["pool"] = (time.perf_counter() - t0) / tasks * 1e3
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, dashboard_address=None)
    with cluster, Client(cluster) as client:
        client.gather(client.map(_noop, range(workers), pure=False))
        t0 = time.perf_counter()
        client.gather(client.map(_noop, range(tasks), pure=False))
        out["dask"] = (time.perf_counter() - t0) / tasks * 1e3
    return out


def _startup_s(kind: str, workers: int) -> float:
    t0 = time.perf_counter()
    if kind == "pool":
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            list(pool.map(abs, range(workers)))
    else:
        from distributed import Client, LocalCluster

        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, dashboard_address=None)
        with cluster, Client(cluster) as client:
            client.gather(client.map(abs, range(workers)))
    return time.perf_counter() - t0


def main() -> int:
    p = parser(__doc__ or "")
    p.add_argument("--cases", type=int, help="cases per runner (default 16; smoke 4)")
    args = p.parse_args()
    cases = args.cases or (4 if args.smoke else 16)
    duration_s = 0.05 if args.smoke else 1.0
    workers = default_workers()
    out: dict[str, Any] = {"scenario_s": duration_s, "workers": workers}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        serial = _timed(folder, "serial", Runner("serial", 1), cases, duration_s, 0)
        pool = _timed(folder, "pool", Runner("pool", workers), cases, duration_s, 0)
        per_worker = -(-cases // workers)  # one task per worker
        dask = _timed(folder, "dask", Runner("dask", workers), cases, duration_s, per_worker)
        dask1 = _timed(folder, "dask1", Runner("dask", workers), cases, duration_s, 1)
        pool_start = _startup_s("pool", workers)
        dask_start = _startup_s("dask", workers)
        task_ms = _per_task_overhead_ms(workers, 50 if args.smoke else 400)
    same = serial["metrics"] == pool["metrics"] == dask["metrics"] == dask1["metrics"]
    for r in (serial, pool, dask, dask1):
        r.pop("metrics")
    efficiency = pool["cases_per_min"] / (workers * serial["cases_per_min"])
    n = serial["cases"]
    out.update({
        "serial": serial,
        "pool": pool,
        "dask_batched": dask,
        "dask_one_case_per_task": dask1,
        "startup_s": {"pool": pool_start, "dask_local_cluster": dask_start},
        "pool_parallel_efficiency": efficiency,
        "dask_minus_pool_per_case_s": (dask["wall_s"] - pool["wall_s"]) / n,
        "dask_minus_pool_per_case_s_after_startup": (
            dask["wall_s"] - dask_start - (pool["wall_s"] - pool_start)
        ) / n,
        "unbatched_minus_batched_per_case_s": (dask1["wall_s"] - dask["wall_s"]) / n,
        "noop_task_overhead_ms": task_ms,
        "identical_metrics": same,
    })  # fmt: skip
    # on paper: 100,000 cases on N dedicated workers at this machine's per-case cost (a worker's
    # own serial rate) and the pool's efficiency, plus the cluster's startup
    per_case_s = serial["wall_s"] / n
    out["case_100k_hours"] = {
        f"{w}_workers": (100_000 * per_case_s / (w * min(1.0, efficiency)) + dask_start) / 3600
        for w in (2, 16, 64, 256)
    }
    out["loadavg_end"] = os.getloadavg()
    report("campaign", out, args.json)
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
