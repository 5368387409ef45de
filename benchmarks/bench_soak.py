"""Soak: a real-time run of N minutes; the loop process's RSS over time, and every sample recorded.

``python -m firmware_sim`` (paper-step, random node id) in its own process over udp_multicast;
``dob-hil run CONFIG -i udp_multicast -c GROUP --duration S --log L --json`` as a child process
whose RSS (``VmRSS`` of ``/proc/<pid>/status``), and that of its log writer process, this
process samples every second from outside (no thread inside the loop). Then the log is read:
its ``seq`` must run 0..planned-1 without a gap, the samples flagged missing must equal the
counts of the ``feedback_lost``/``overrun_skip`` events, the log must be complete with zero
records dropped.

Goal: the loop process's RSS flat: growth <= 10 MB after the first 10 s (of the process); every
sample recorded.

    .venv/bin/python benchmarks/bench_soak.py [--smoke] [--json] [--minutes N]
        [--sched-fifo] [--cpu N] [--freeze-gc] [--drive-cpu N] [--spin-us US]
        [--patience-periods N] [--keep-log PATH]
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from _common import parser, report
from _rt_common import (
    Unavailable,
    accounting,
    child_env,
    node_config,
    private_udp_port,
    skip,
    standalone_drive,
    timing_figures,
    udp_channel,
)

from dob_hil.config import load_config
from dob_hil.log import read_log

SETTLE_S = 10.0
GROWTH_GOAL_MB = 10.0


def dob_hil_command() -> list[str]:
    script = Path(os.path.normpath(sys.executable)).with_name("dob-hil")
    return [str(script)] if script.exists() else [sys.executable, "-m", "dob_hil.cli"]


def rss_kib(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except (OSError, ValueError):
        return None
    return None


def children(pid: int) -> list[int]:
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as f:
            return [int(c) for c in f.read().split()]
    except OSError:
        return []


def growth(series: list[tuple[float, int | None]]) -> dict[str, Any]:
    """RSS figures (MB) of ``(seconds since start, KiB)`` points: growth after SETTLE_S."""
    values = [(t, v) for t, v in series if v is not None]
    after = [v for t, v in values if t >= SETTLE_S]
    out: dict[str, Any] = {
        "first_MB": round(values[0][1] / 1024, 1) if values else None,
        "peak_MB": round(max(v for _, v in values) / 1024, 1) if values else None,
    }
    if not after:
        out["growth_after_10s_MB"] = None
        out["note"] = f"run shorter than {SETTLE_S:g} s: no growth figure"
        return out
    base = after[0]
    out.update(
        {
            "at_10s_MB": round(base / 1024, 1),
            "last_MB": round(after[-1] / 1024, 1),
            "growth_after_10s_MB": round((max(after) - base) / 1024, 2),
            "last_minus_10s_MB": round((after[-1] - base) / 1024, 2),
            "samples_after_10s": len(after),
        }
    )
    return out


def main() -> None:
    p = parser(__doc__ or "")
    p.add_argument("--minutes", type=float, help="run length (default 10, smoke 0.02)")
    p.add_argument("--sched-fifo", action="store_true", help="dob-hil run --sched-fifo")
    p.add_argument("--cpu", type=int, action="append", help="dob-hil run --cpu N (repeatable)")
    p.add_argument("--freeze-gc", action="store_true", help="dob-hil run --freeze-gc")
    p.add_argument("--drive-cpu", type=int, help="pin firmware_sim to this CPU")
    p.add_argument("--spin-us", type=float, help="firmware_sim --spin-us (default: its own, 100)")
    p.add_argument(
        "--patience-periods", type=int, help="watchdog/host timeout; 0: keep 10 (200; smoke 10000)"
    )
    p.add_argument("--keep-log", type=Path, help="copy the run's MCAP log here")
    args = p.parse_args()
    minutes = args.minutes if args.minutes is not None else (0.02 if args.smoke else 10.0)
    duration_s = minutes * 60.0
    port = private_udp_port()
    try:
        channel = udp_channel()
    except Unavailable as exc:
        skip(str(exc))
    node_id = random.randint(2, 15)  # the native protocol has nodes 0..15
    with tempfile.TemporaryDirectory(prefix="bench-soak-") as tmp_name:
        tmp = Path(tmp_name)
        patience = args.patience_periods
        if patience is None:
            patience = 10_000 if args.smoke else 200  # the smoke run is part of the loaded test suite
        cfg_path = node_config(tmp, node_id, patience or None)
        config = load_config(cfg_path)
        log_path = tmp / "soak.mcap"
        cmd = [*dob_hil_command(), "run", str(cfg_path), "-i", "udp_multicast", "-c", channel,
               "--duration", f"{duration_s:g}", "--log", str(log_path), "--no-progress",
               "--json"]  # fmt: skip
        if args.sched_fifo:
            cmd.append("--sched-fifo")
        for cpu in args.cpu or ():
            cmd += ["--cpu", str(cpu)]
        if args.freeze_gc:
            cmd.append("--freeze-gc")
        series: list[tuple[float, int, int | None]] = []  # (s since start, loop KiB, writer KiB)
        with standalone_drive(cfg_path, channel, spin_us=args.spin_us, cpu=args.drive_cpu) as drive:
            with (tmp / "run.out").open("wb") as out, (tmp / "run.err").open("wb") as err:
                t0 = time.monotonic()
                proc = subprocess.Popen(cmd, stdout=out, stderr=err, env=child_env())
                next_t = t0
                while proc.poll() is None:
                    loop_kib = rss_kib(proc.pid)
                    kids = children(proc.pid)
                    writer_kib = rss_kib(kids[0]) if kids else None
                    if loop_kib is not None:
                        series.append((time.monotonic() - t0, loop_kib, writer_kib))
                    next_t += 1.0
                    with contextlib.suppress(subprocess.TimeoutExpired):
                        proc.wait(timeout=max(0.0, next_t - time.monotonic()))
            drive_alive = drive.alive()
        run_out = (tmp / "run.out").read_text()
        run_err = (tmp / "run.err").read_text(errors="replace").strip()
        if proc.returncode != 0 or not log_path.exists():
            print(f"bench_soak: dob-hil run failed (status {proc.returncode}): {run_err}", file=sys.stderr)
            sys.exit(1)
        summary = json.loads(run_out)
        data = read_log(log_path)
        acc = accounting(data, summary["planned_samples"])
        timing = timing_figures(data, config.plant.period_ns)
        if args.keep_log is not None:
            shutil.copyfile(log_path, args.keep_log)
    loop_rss = growth([(t, loop) for t, loop, _ in series])
    writer_rss = growth([(t, writer) for t, _, writer in series])
    g = loop_rss["growth_after_10s_MB"]
    report(
        "soak: real-time run over udp_multicast, loop RSS and completeness",
        {
            "minutes": minutes,
            "command": " ".join(cmd),
            "udp_port": f"{port} (CAN_CONFIG)",
            "exit_reason": summary["exit_reason"],
            "rt_refused": summary["rt_refused"],
            "drive": {"alive_at_end": drive_alive, "summary": drive.last_line()},
            "rss_samples": len(series),
            "loop_rss": loop_rss,
            "writer_rss": writer_rss,
            **{f"log {k}": v for k, v in acc.items()},
            "overrun_pct": timing["overrun_pct"],
            "latency_us": timing["latency_us"],
            "goals_met": {
                "rss_growth_le_10MB": None if g is None else g <= GROWTH_GOAL_MB,
                "every_sample_recorded": acc["all_recorded"],
            },
            "goal": "loop RSS growth <= 10 MB after the first 10 s; every sample recorded",
        },
        args.json,
    )


if __name__ == "__main__":
    main()
