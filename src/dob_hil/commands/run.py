"""``dob-hil run``: one run against a drive; with no bus, the embedded simulated drive in lockstep."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
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


def _plural(n: object, word: str) -> str:
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def format_summary(s: dict[str, object]) -> str:
    """The run summary as text. Counts: ``missing`` samples had no fresh feedback (the policy
    stood in); ``of them in sequence gaps``: feedback frames never seen (lost or overrun)."""
    realtime = s["mode"] != "lockstep"
    span = "run time" if realtime else "simulated"
    lines = [
        f"run {s['name']}: {s['exit_reason']}  ({s['mode']}, DOB {'on' if s['dob_enabled'] else 'off'})",
        f"  samples          {s['samples']} of {s['planned_samples']} ({s['duration_s']:.3f} s {span}, "
        f"{s['wall_time_s']:.2f} s wall, {s['samples_per_s']:,.0f} samples/s)",
        f"  current          max |u| {s['max_abs_current_A']:.4f} A (limit {s['current_limit_A']} A), "
        f"saturated {_plural(s['saturated_samples'], 'sample')}",
        f"  feedback         missing {_plural(s['missing_samples'], 'sample')} "
        f"({s['skipped_samples']} of them in sequence gaps), "
        f"{_plural(s['overruns'], 'overrun')}",
        f"  controller step  max {int(s['compute_ns_max']) / 1000:.1f} us "  # type: ignore[call-overload]
        "(step, limit, quantise, predict; bench_step.py times the step alone)",
        f"  log              {s['log_path']} (dropped records: {s['log_dropped_records']})",
    ]
    if s.get("live"):
        lv = s["live"]
        lines.append(
            f"  live view        port {lv['port']}: {lv['forwarded']} items sent, "  # type: ignore[index]
            f"{lv['dropped']} dropped (live process behind)"  # type: ignore[index]
        )
    if s["events"]:
        lines.append(f"  link events      {s['events']}")
    for msg in s["rt_refused"]:  # type: ignore[attr-defined]
        lines.append(f"  not applied      {msg}")
    return "\n".join(lines)


def check_run_arguments(args: argparse.Namespace, config: Config) -> None:
    """The command line's own values, checked like the config's before anything is opened."""
    from dob_hil.commands.paths import ensure_dir, ensure_file_parent
    from dob_hil.config import check_cpus, check_value

    if args.duration is not None:
        check_value("run", "duration_s", args.duration, "--duration")
    if args.cpu:
        check_cpus(args.cpu, "--cpu")
    elif config.run.cpu_affinity:  # the config's CPUs, on the machine that runs it
        check_cpus(config.run.cpu_affinity, "run.cpu_affinity")
    if args.log:
        ensure_file_parent(Path(args.log), "--log")
    else:
        ensure_dir(config.run.log_dir, "run.log_dir")


def _live_options(args: argparse.Namespace) -> object:
    """``--live [PORT]``, ``--live-host``, ``--live-rate``; None without ``--live``."""
    if getattr(args, "live", None) is None:
        return None
    import sys

    from dob_hil.live.process import LiveOptions

    def announce(host: str, port: int) -> None:
        print(f"dob-hil run: live view on ws://{host}:{port} (Foxglove: Open connection)", file=sys.stderr)

    options = LiveOptions(port=args.live, host=args.live_host, rate_hz=args.live_rate, on_ready=announce)
    options.check()
    return options


def main(args: argparse.Namespace) -> int:
    from dob_hil.commands.progress import ProgressBar
    from dob_hil.loop.rt_os import RtSettings
    from dob_hil.loop.session import RunOptions, run_session

    config = load_run_config(args)
    check_run_arguments(args, config)
    if args.no_log and args.log:
        raise ConfigError("--no-log", "give --log PATH or --no-log, not both")
    bar = ProgressBar(
        f"{config.name}{' (no DOB)' if args.no_dob else ''}",
        not args.no_progress and not args.json,
        force=args.progress,
    )
    options = RunOptions(
        interface=args.interface,
        channel=args.channel,
        bitrate=args.bitrate,
        dob_enabled=False if args.no_dob else None,
        duration_s=args.duration,
        log_path=Path(os.devnull) if args.no_log else (Path(args.log) if args.log else None),
        log_layout=args.log_layout,
        realtime=args.realtime,
        rt=RtSettings(
            sched_fifo=args.sched_fifo, cpus=tuple(args.cpu) if args.cpu else None, freeze_gc=args.freeze_gc
        ),
        progress=bar if bar.enabled else None,
        live=_live_options(args),
    )
    try:
        summary = run_session(config, options)
    except BaseException:
        bar.finish()
        raise
    bar.finish(summary.samples, summary.planned_samples)
    d = summary.to_dict()
    if args.json:
        print(json.dumps(d, indent=2))
    else:
        print(format_summary(d))
    # the shell's convention for a process ended by a signal: 128 + the signal number
    signal_exit = {"SIGINT": 130, "SIGTERM": 143}
    return 0 if summary.exit_reason == "completed" else signal_exit.get(summary.exit_reason, 1)
