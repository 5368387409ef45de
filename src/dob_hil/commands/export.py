"""``dob-hil export LOG.mcap --format blf|asc|csv [--out PATH] [--samples]``.

Writes the log's raw CAN frames through python-can's writers (BLF and ASC open in CANalyzer,
CANoe, SavvyCAN; all three read back with ``can.LogReader``), or with ``--samples`` (csv only)
the samples, one column per scalar field. Default output beside the log: ``<stem>.blf``,
``<stem>.asc``, ``<stem>-frames.csv``, ``<stem>-samples.csv``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from dob_hil.errors import ConfigError


def main(args: argparse.Namespace) -> int:
    from dob_hil.analysis.export import default_export_path, export_frames, write_frames, write_samples_csv
    from dob_hil.log import read_log
    from dob_hil.log.schemas import TOPIC_CAN, TOPIC_CAN_FD, TOPIC_SAMPLE
    from dob_hil.log.wallclock import wall_offset_ns

    if args.samples and args.format != "csv":
        raise ConfigError("--samples", f"samples are exported as csv only, not {args.format}")
    log_path = Path(args.log)
    out = Path(args.out) if args.out else default_export_path(log_path, args.format, args.samples)
    if out.resolve() == log_path.resolve():
        raise ConfigError("--out", f"{out} is the log itself")
    data = read_log(log_path, topics=(TOPIC_SAMPLE,) if args.samples else (TOPIC_CAN, TOPIC_CAN_FD))
    for warning in data.warnings:
        print(f"dob-hil export: warning: {log_path}: {warning}", file=sys.stderr)
    if args.samples:
        n = write_samples_csv(data.samples, out)
        print(f"{out}: {n} samples")
    else:
        starts = [int(a["timestamp_ns"].min()) for a in (data.frames, data.fd_frames) if len(a)]
        offset_ns = wall_offset_ns(data.metadata, min(starts) if starts else None)
        frames, fd_frames, echoes = export_frames(data.frames, data.fd_frames, wall_offset_ns=offset_ns)
        n = write_frames(frames, fd_frames, out, args.format)
        dropped = f", {echoes} received copies of own frames left out" if echoes else ""
        print(f"{out}: {n} frames ({args.format}){dropped}")
    return 0
