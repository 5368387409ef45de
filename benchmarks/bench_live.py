"""``--live`` costs the loop nothing it can feel: real time, Ts = 300 us, with and without a viewer.

The loop runs against firmware_sim in its own process over udp_multicast (as bench_realtime.py),
logging on, in four modes, interleaved round by round so that the machine's load drifts alike
over all of them:

- ``off``: no ``--live``;
- ``live_no_client``: ``--live`` (100 samples/s to the live-server process), nobody connected;
- ``live_client``: a viewer process connected and subscribed to every channel, reading all;
- ``live_stalled_client``: a viewer process subscribed that never reads (its socket fills).

Per mode (the median over rounds of each round's figure): feedback-to-command latency
(``tx_time_ns - rx_time_ns``) p50/p99, the controller step time p50/p99, overruns (% of cycles),
and the ratio of each latency percentile against ``off`` timed in the same run. Goal: with a
viewer connected (fast or stalled), latency p50 and p99 within 1.2x of ``off``.

``tap_cost``: the control thread's own price, free of the run's noise: ``LogWriter.sample``
against ``TappedLogWriter.sample`` feeding a running live server, per call (median of chunks).

    .venv/bin/python benchmarks/bench_live.py [--smoke] [--json] [--duration S] [--rounds N]
"""

from __future__ import annotations

import random
import subprocess
import sys
import tempfile
from pathlib import Path
from statistics import median
from typing import Any

from _common import parser, report
from _rt_common import (
    BENCH_DIR,
    Unavailable,
    child_env,
    node_config,
    private_udp_port,
    skip,
    standalone_drive,
    timing_figures,
    udp_channel,
)

from dob_hil.config import load_config
from dob_hil.live.process import LiveOptions
from dob_hil.log import read_log
from dob_hil.loop.session import RunOptions, run_session

MODES = ("off", "live_no_client", "live_client", "live_stalled_client")
RATIO_GOAL = 1.2
PATIENCE_PERIODS = 2000  # watchdog/host timeout: a loaded machine's stall is measured, not fatal


def _run(mode: str, cfg_path: Path, channel: str, duration_s: float, log_path: Path) -> dict[str, Any]:
    config = load_config(cfg_path)
    viewers: list[subprocess.Popen[str]] = []

    def start_viewer(host: str, port: int) -> None:  # the server listens; the drive is not enabled yet
        if mode not in ("live_client", "live_stalled_client"):
            return
        cmd = [sys.executable, str(BENCH_DIR / "_live_client.py"), str(port)]
        if mode == "live_stalled_client":
            cmd.append("--slow")
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, env=child_env())
        viewers.append(proc)
        assert proc.stdout is not None
        line = proc.stdout.readline().strip()
        if line != "subscribed":
            raise RuntimeError(f"viewer did not subscribe: {line!r}")

    live = None if mode == "off" else LiveOptions(port=0, linger_s=0.0, on_ready=start_viewer)
    try:
        with standalone_drive(cfg_path, channel):
            summary = run_session(
                config,
                RunOptions(
                    interface="udp_multicast", channel=channel, duration_s=duration_s,
                    log_path=log_path, enable_timeout_s=15.0, live=live,
                ),
            )  # fmt: skip
    finally:
        received = None
        for proc in viewers:
            if mode == "live_stalled_client":
                proc.kill()
            try:
                out, _ = proc.communicate(timeout=60)
                if out.strip().startswith("received"):
                    received = int(out.split()[-1])
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.communicate()
    timing = timing_figures(read_log(log_path), config.plant.period_ns)
    return {
        "exit_reason": summary.exit_reason,
        "latency_us": timing["latency_us"],
        "compute_us": timing["compute_us"],
        "overrun_pct": timing["overrun_pct"],
        "live": summary.live,
        "viewer_received": received,
    }


def _median_of(rounds: list[dict[str, Any]], key: str, q: str) -> float | None:
    values = [r[key][q] for r in rounds if r[key] is not None]
    return round(median(values), 1) if values else None


def _tap_cost(calls: int, chunks: int) -> dict[str, Any]:
    """What the control thread pays per sample for the tap: ``LogWriter.sample`` (no file: packing
    only) against ``TappedLogWriter.sample`` feeding a running live server at 100 samples/s of a
    Ts = 300 us run (every 33rd call is put on the queue), interleaved chunk by chunk."""
    import os
    import time

    from dob_hil.live.process import LiveServer
    from dob_hil.live.tap import TappedLogWriter
    from dob_hil.log import LogWriter
    from dob_hil.log.schemas import LogLayout

    layout = LogLayout(n_states=4, n_inputs=1, n_outputs=1, n_plant_states=2)
    n = layout.n_states
    args = (1, 2, 3, 4, (5,), (0.1,), (0.2,) * n, (0.3,) * n, (0.4,) * n, (0.5,), (0.6,), (0.7,), (0.7,),
            9, 10, (11,), 12, 8)  # fmt: skip
    with LiveServer(LiveOptions(port=0, linger_s=0.0), layout, 300_000, "{}", {}) as live:
        plain = LogWriter(Path(os.devnull), layout)
        tapped = TappedLogWriter(Path(os.devnull), layout, tap=live.tap)
        per: dict[str, list[float]] = {"plain": [], "tapped": []}
        for _ in range(chunks):
            for name, w in (("plain", plain), ("tapped", tapped)):
                sample = w.sample
                t0 = time.perf_counter_ns()
                for k in range(calls):
                    sample(*args[:13], k, *args[14:])
                per[name].append((time.perf_counter_ns() - t0) / calls)
                w.flush(force=True)
        plain.close()
        tapped.close()
        stats = live.tap.stats.as_dict()
    p50 = {k: round(median(v), 1) for k, v in per.items()}
    return {
        "sample_call_ns_p50_plain": p50["plain"],
        "sample_call_ns_p50_tapped": p50["tapped"],
        "tap_extra_ns_per_sample": round(p50["tapped"] - p50["plain"], 1),
        "ratio": round(p50["tapped"] / p50["plain"], 2),
        "live_items": stats,
    }


def _ratio(value: float | None, base: float | None) -> float | None:
    return round(value / base, 2) if value is not None and base else None


def main() -> None:
    p = parser(__doc__ or "")
    p.add_argument("--duration", type=float, help="seconds per run (default 10, smoke 0.5)")
    p.add_argument("--rounds", type=int, help="rounds of the four modes (default 3, smoke 1)")
    args = p.parse_args()
    duration_s = args.duration if args.duration is not None else (0.5 if args.smoke else 10.0)
    rounds = args.rounds if args.rounds is not None else (1 if args.smoke else 3)
    port = private_udp_port()
    try:
        channel = udp_channel()
    except Unavailable as exc:
        skip(str(exc))
    per_mode: dict[str, list[dict[str, Any]]] = {m: [] for m in MODES}
    with tempfile.TemporaryDirectory(prefix="bench-live-") as tmp_name:
        tmp = Path(tmp_name)
        cfg_path = node_config(tmp, random.randint(2, 15), PATIENCE_PERIODS)
        for r in range(rounds):
            for mode in MODES:
                print(f"bench_live: round {r + 1}/{rounds}: {mode}", file=sys.stderr, flush=True)
                per_mode[mode].append(_run(mode, cfg_path, channel, duration_s, tmp / f"{mode}-{r}.mcap"))
    result: dict[str, Any] = {"duration_s": duration_s, "rounds": rounds, "channel": f"{channel} port {port}"}
    result["tap_cost"] = _tap_cost(2_000 if args.smoke else 20_000, 5 if args.smoke else 25)
    base = {q: _median_of(per_mode["off"], "latency_us", q) for q in ("p50", "p99")}
    met: dict[str, bool | None] = {}
    for mode, runs in per_mode.items():
        lat = {q: _median_of(runs, "latency_us", q) for q in ("p50", "p99")}
        ratio = {q: _ratio(lat[q], base[q]) for q in ("p50", "p99")}
        result[mode] = {
            "latency_p50_us": lat["p50"],
            "latency_p99_us": lat["p99"],
            "ratio_p50": ratio["p50"],
            "ratio_p99": ratio["p99"],
            "compute_p50_us": _median_of(runs, "compute_us", "p50"),
            "compute_p99_us": _median_of(runs, "compute_us", "p99"),
            "overrun_pct": round(median(r["overrun_pct"] for r in runs), 3),
            "exit": ",".join(sorted({r["exit_reason"] for r in runs})),
            "live_forwarded": sum((r["live"] or {}).get("forwarded", 0) for r in runs),
            "live_dropped": sum((r["live"] or {}).get("dropped", 0) for r in runs),
            "viewer_received": sum(r["viewer_received"] or 0 for r in runs),
        }
        if mode in ("live_client", "live_stalled_client"):
            met[f"{mode}_within_{RATIO_GOAL}x"] = (
                None if None in ratio.values() else all(v <= RATIO_GOAL for v in ratio.values())  # type: ignore[operator]
            )
    result["goals_met"] = met
    result["goal"] = f"with a viewer (fast or stalled): latency p50 and p99 within {RATIO_GOAL}x of off"
    report("--live: loop latency with and without a viewer (real time, Ts = 300 us)", result, args.json)
    if any(r["exit_reason"] != "completed" for runs in per_mode.values() for r in runs):
        print("bench_live: a session ended early", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
