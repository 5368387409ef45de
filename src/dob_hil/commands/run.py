"""``dob-hil run``: one run against a drive; with no bus, the embedded simulated drive in lockstep."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

from dob_hil.config import Config, load_config
from dob_hil.errors import ConfigError
from dob_hil.scenarios import resolve_config_path, scenario_path


def load_run_config(args: argparse.Namespace) -> Config:
    if args.scenario and args.config:
        raise ConfigError("--scenario", "give a config file or --scenario, not both")
    if args.scenario:
        return _drive_overrides(load_config(scenario_path(args.scenario)), args)
    if not args.config:
        raise ConfigError("config", "missing: give a config file or --scenario NAME")
    return _drive_overrides(load_config(resolve_config_path(args.config)), args)


def _drive_overrides(config: Config, args: argparse.Namespace) -> Config:
    """--clear-fault, --feedback-timeout-periods and --watchdog-periods over the [drive] section."""
    changes: dict[str, object] = {}
    flags = (
        ("--feedback-timeout-periods", "feedback_timeout_periods"),
        ("--watchdog-periods", "watchdog_periods"),
    )
    for flag, key in flags:
        value = getattr(args, key, None)
        if value is not None:
            if not 1 <= value <= 100_000:
                raise ConfigError(flag, f"must be 1..100000 periods, got {value}")
            changes[key] = value
    if getattr(args, "clear_fault", False):
        changes["clear_fault"] = True
    if not changes:
        return config
    return dataclasses.replace(config, drive=dataclasses.replace(config.drive, **changes))  # type: ignore[arg-type]


class ProgressBar:
    """A one-line progress bar on stderr, drawn at most 10 times a second."""

    def __init__(self, label: str, enabled: bool) -> None:
        self._label = label
        self._enabled = enabled
        self._last = 0.0
        self._t0 = time.perf_counter()

    def __call__(self, done: int, total: int) -> None:
        if not self._enabled:
            return
        now = time.perf_counter()
        if now - self._last < 0.1 and done < total:
            return
        self._last = now
        frac = done / total if total else 1.0
        bar = "#" * int(30 * frac)
        rate = done / (now - self._t0) if now > self._t0 else 0.0
        print(
            f"\r{self._label} [{bar:<30}] {100 * frac:5.1f}% {rate:,.0f} samples/s", end="", file=sys.stderr
        )

    def close(self) -> None:
        if self._enabled and self._last:
            print(file=sys.stderr)


def format_summary(s: dict[str, object]) -> str:
    lines = [
        f"run {s['name']}: {s['exit_reason']}  ({s['mode']}, DOB {'on' if s['dob_enabled'] else 'off'})",
        f"  samples          {s['samples']} of {s['planned_samples']} ({s['duration_s']:.3f} s simulated, "
        f"{s['wall_time_s']:.2f} s wall, {s['samples_per_s']:,.0f} samples/s)",
        f"  current          max |u| {s['max_abs_current_A']:.4f} A (limit {s['current_limit_A']} A), "
        f"saturated {s['saturated_samples']} samples",
        f"  feedback         missing {s['missing_samples']}, skipped {s['skipped_samples']}, "
        f"overruns {s['overruns']}",
        f"  controller step  max {int(s['compute_ns_max']) / 1000:.1f} us",  # type: ignore[call-overload]
        f"  log              {s['log_path']} (dropped records: {s['log_dropped_records']})",
    ]
    if s["events"]:
        lines.append(f"  link events      {s['events']}")
    for msg in s["rt_refused"]:  # type: ignore[attr-defined]
        lines.append(f"  not applied      {msg}")
    return "\n".join(lines)


def main(args: argparse.Namespace) -> int:
    from dob_hil.loop.rt_os import RtSettings
    from dob_hil.loop.session import RunOptions, run_session

    config = load_run_config(args)
    bar = ProgressBar(
        f"{config.name}{' (no DOB)' if args.no_dob else ''}", not args.no_progress and not args.json
    )
    options = RunOptions(
        interface=args.interface,
        channel=args.channel,
        bitrate=args.bitrate,
        dob_enabled=False if args.no_dob else None,
        duration_s=args.duration,
        log_path=Path(args.log) if args.log else None,
        realtime=args.realtime,
        rt=RtSettings(
            sched_fifo=args.sched_fifo, cpus=tuple(args.cpu) if args.cpu else None, freeze_gc=args.freeze_gc
        ),
        progress=bar if (args.duration or config.run.duration_s) >= 5.0 else None,
    )
    try:
        summary = run_session(config, options)
    finally:
        bar.close()
    d = summary.to_dict()
    if args.json:
        print(json.dumps(d, indent=2))
    else:
        print(format_summary(d))
    # the shell's convention for a process ended by a signal: 128 + the signal number
    signal_exit = {"SIGINT": 130, "SIGTERM": 143}
    return 0 if summary.exit_reason == "completed" else signal_exit.get(summary.exit_reason, 1)
