"""The CiA 402 profile: lockstep throughput against the native profile, and real-time SYNC jitter.

1. Lockstep, in the same run (interleaved): ``run_session`` of paper-step (native: FEEDBACK /
   COMMAND) and of paper-step-cia402 (SYNC / TPDO1 / RPDO1 against firmware_sim's CiA 402 drive),
   full stack with logging; samples/s of each (median of the repeats) and their ratio.
2. Real time, Ts = 300 us: paper-step-cia402 against ``python -m firmware_sim`` (its CiA 402
   drive) in another process over udp_multicast on a private UDP port. The host sends each SYNC
   at an absolute deadline (sleep, then spin the last 100 us); the log's ``lateness_ns`` of each
   sample is the SYNC's send time (after ``bus.send`` returned) minus its deadline: p50/p99/max.
   Beside it: missed TPDOs, skipped deadlines (overruns) and the SYNC-to-TPDO time.

    .venv/bin/python benchmarks/bench_cia402.py [--smoke] [--json] [--duration S]
"""

from __future__ import annotations

import random
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from _common import median, parser, percentiles, report
from _rt_common import Unavailable, private_udp_port, skip_counts, standalone_drive, udp_channel

from dob_hil.config import load_config
from dob_hil.log import read_log
from dob_hil.log.schemas import FLAG_FEEDBACK_MISSING
from dob_hil.loop.session import RunOptions, run_session
from dob_hil.scenarios import scenario_path, scenario_variant


def lockstep_samples_per_s(name: str, duration_s: float, path: Path) -> float:
    summary = run_session(load_config(scenario_path(name)), RunOptions(duration_s=duration_s, log_path=path))
    return summary.samples / summary.wall_time_s


def _us(values: np.ndarray[Any, Any]) -> dict[str, float] | None:
    if len(values) == 0:
        return None
    p = percentiles((values.astype(np.float64) / 1000).tolist(), (50, 99))
    return {k: round(v, 1) for k, v in p.items() if k != "min"}


def realtime_sync_jitter(duration_s: float, tmp: Path) -> dict[str, Any]:
    port = private_udp_port()
    channel = udp_channel()
    node_id = random.randint(2, 120)
    cfg = scenario_variant("paper-step-cia402", tmp, node_id=node_id, patience_periods=1000)
    config = load_config(cfg)
    log_path = tmp / "rt.mcap"
    with standalone_drive(cfg, channel):
        summary = run_session(
            config,
            RunOptions(interface="udp_multicast", channel=channel, duration_s=duration_s, log_path=log_path,
                       enable_timeout_s=15.0),
        )  # fmt: skip
    s = read_log(log_path).samples
    sent = s["tx_time_ns"] > 0  # a SYNC went out for the sample (skipped deadlines have none)
    answered = sent & ((s["flags"] & FLAG_FEEDBACK_MISSING) == 0)
    sync_ns = s["time_ns"].astype(np.int64) + s["lateness_ns"].astype(np.int64)
    skips = skip_counts(read_log(log_path), len(s))
    return {
        "udp_port": port,
        "exit_reason": summary.exit_reason,
        "samples": len(s),
        "sync_lateness_us": _us(s["lateness_ns"][sent]),
        "sync_to_tpdo_us": _us(s["rx_time_ns"][answered].astype(np.int64) - sync_ns[answered]),
        "missed_tpdo": int(np.count_nonzero(sent & ~answered)),
        "skipped_deadlines": skips["overrun_skip"],
        "missed_tpdo_pct": 100.0 * np.count_nonzero(sent & ~answered) / max(1, len(s)),
    }


def main() -> None:
    p = parser(__doc__ or "")
    p.add_argument("--duration", type=float, default=None, help="seconds of the real-time run")
    args = p.parse_args()
    repeats = 2 if args.smoke else 5
    lock_s = 0.3 if args.smoke else 5.0
    rt_s = args.duration or (0.5 if args.smoke else 10.0)
    native, cia402 = [], []
    result: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        for i in range(repeats):  # interleaved: both see the same machine state
            native.append(lockstep_samples_per_s("paper-step", lock_s, tmp / f"n{i}.mcap"))
            cia402.append(lockstep_samples_per_s("paper-step-cia402", lock_s, tmp / f"c{i}.mcap"))
        result["lockstep_samples_per_s"] = {
            "native_median": round(median(native)),
            "cia402_median": round(median(cia402)),
            "cia402_over_native": round(median(cia402) / median(native), 3),
            "repeats": repeats,
            "seconds_each": lock_s,
        }
        try:
            result["realtime_cia402_udp_multicast"] = realtime_sync_jitter(rt_s, tmp)
        except Unavailable as exc:
            result["realtime_cia402_udp_multicast"] = f"skipped: {exc}"
    report("cia402 profile: lockstep vs native, real-time SYNC jitter", result, args.json)


if __name__ == "__main__":
    main()
