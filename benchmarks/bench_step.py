"""The pure controller step (paper design) vs a straightforward numpy implementation, same run.

Times ``update`` + ``predict`` of the generated step and of ``numpy_step`` + ``numpy_predict``
on the paper's design, in batches (per-call times from batches of 1000 calls, so the timer's own
cost is amortised), interleaved. Goal: median <= 1 us and >= 10x faster than numpy.

    .venv/bin/python benchmarks/bench_step.py [--smoke] [--json]
"""

from __future__ import annotations

import time

import numpy as np
from _common import median, parser, percentiles, report

from dob_hil.config import load_config
from dob_hil.control.step import Gains, compile_step, numpy_predict, numpy_step
from dob_hil.design import build_design
from dob_hil.scenarios import scenario_path

BATCH = 1000


def main() -> None:
    args = parser(__doc__ or "").parse_args()
    batches = 50 if args.smoke else 2000
    design = build_design(load_config(scenario_path("paper-step")))
    g = Gains(design.Phi, design.Gam, design.C, design.Lc, design.Kc, design.Kdist)
    f = compile_step(g, True)
    update, predict = f.update, f.predict
    x_bar, y, x_ref, u_applied = (0.1, 0.2), (0.15,), (1.0, 0.0), (0.5,)
    xb_np, y_np, xr_np, ua_np = (
        np.array(v, dtype=float).reshape(-1, 1) for v in (x_bar, y, x_ref, u_applied)
    )
    fast, slow = [], []
    for _ in range(batches):
        t0 = time.perf_counter_ns()
        for _ in range(BATCH):
            out = update(x_bar, y, x_ref)
            predict(out.x_hat, u_applied, out.u_dist)
        fast.append((time.perf_counter_ns() - t0) / BATCH)
        t0 = time.perf_counter_ns()
        for _ in range(BATCH // 10):
            x_hat, _u_fb, u_dist, _u = numpy_step(g, True, xb_np, y_np, xr_np)
            numpy_predict(g, x_hat, ua_np, u_dist)
        slow.append((time.perf_counter_ns() - t0) / (BATCH // 10))
    report(
        "controller step (update + predict), paper design",
        {
            "calls": batches * BATCH,
            "generated_step_ns": percentiles(fast),
            "numpy_step_ns": percentiles(slow),
            "median_us": median(fast) / 1000,
            "speedup_vs_numpy": median(slow) / median(fast),
            "goal": "median <= 1 us and >= 10x faster than numpy",
        },
        args.json,
    )


if __name__ == "__main__":
    main()
