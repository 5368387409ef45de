"""Lockstep full stack vs a bare two-frame exchange on python-can's virtual bus, in the same run.

Full stack: firmware_sim + the lockstep bus + controller + MCAP logging of samples, frames and
ground truth (``run_session`` on the paper-step scenario), on the default in-process bus
(``RunOptions.bus_impl = "inprocess"``: python-can ``BusABC``, no copies) and, for comparison, on
python-can's ``virtual``. Baseline: one thread sends a 6-byte frame on one end of a python-can
virtual bus, receives it on the other end, answers with a 3-byte frame and receives that: the two
frames of a cycle and nothing else. Goal (issue 16): the full stack with logging at least as fast
as the bare exchange (ratio <= 1.0), on every profile.

    .venv/bin/python benchmarks/bench_lockstep.py [--smoke] [--json]
"""

from __future__ import annotations

import tempfile
import time
import uuid
from pathlib import Path

import can
from _common import median, parser, report

from dob_hil.config import load_config
from dob_hil.loop.session import RunOptions, run_session
from dob_hil.scenarios import scenario_path


def bare_exchange_us(n: int) -> float:
    channel = f"bench-{uuid.uuid4().hex}"
    host = can.Bus(interface="virtual", channel=channel)
    drive = can.Bus(interface="virtual", channel=channel)
    try:
        fb = bytes(6)
        cmd = bytes(3)
        t0 = time.perf_counter_ns()
        for _ in range(n):
            drive.send(can.Message(arbitration_id=0x181, data=fb, is_extended_id=False))
            host.recv(0.0)
            host.send(can.Message(arbitration_id=0x201, data=cmd, is_extended_id=False))
            drive.recv(0.0)
        return (time.perf_counter_ns() - t0) / n / 1000.0
    finally:
        host.shutdown()
        drive.shutdown()


def full_stack_us(duration_s: float, tmp: Path, i: int, bus_impl: str) -> tuple[float, int]:
    config = load_config(scenario_path("paper-step"))
    path = tmp / f"lockstep-{bus_impl}-{i}.mcap"
    summary = run_session(config, RunOptions(duration_s=duration_s, log_path=path, bus_impl=bus_impl))
    path.unlink()
    return summary.wall_time_s / summary.samples * 1e6, summary.log_dropped_records


def main() -> None:
    args = parser(__doc__ or "").parse_args()
    repeats = 2 if args.smoke else 7
    duration_s = 0.3 if args.smoke else 10.0
    n_bare = 2_000 if args.smoke else 50_000
    bare: list[float] = []
    full: list[float] = []
    virtual: list[float] = []
    dropped = 0
    with tempfile.TemporaryDirectory() as d:
        for i in range(repeats):  # interleaved, so all see the same machine state
            bare.append(bare_exchange_us(n_bare))
            us, drop = full_stack_us(duration_s, Path(d), i, "inprocess")
            full.append(us)
            us_v, drop_v = full_stack_us(duration_s, Path(d), i, "virtual")
            virtual.append(us_v)
            dropped += drop + drop_v
    bare_us, full_us, virtual_us = median(bare), median(full), median(virtual)
    ratios = [f / b for f, b in zip(full, bare, strict=True)]  # per repeat: same machine state
    report(
        "lockstep full stack vs bare virtual-bus exchange",
        {
            "repeats": repeats,
            "samples_per_run": round(duration_s / 300e-6),
            "bare_exchange_us": {"median": bare_us, "min": min(bare), "max": max(bare)},
            "full_stack_us_per_sample": {"median": full_us, "min": min(full), "max": max(full)},
            "full_stack_samples_per_s": 1e6 / full_us,
            "ratio_full_over_bare": {"median": median(ratios), "min": min(ratios), "max": max(ratios)},
            "full_stack_on_virtual_us_per_sample": {"median": virtual_us, "ratio": virtual_us / bare_us},
            "log_dropped_records": dropped,
            "goal": "ratio full/bare <= 1.0",
        },
        args.json,
    )


if __name__ == "__main__":
    main()
