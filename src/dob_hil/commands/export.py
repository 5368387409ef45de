"""``dob-hil export LOG.mcap --format blf|asc|csv [--out PATH] [--samples]``, and
``dob-hil export LOG.mcap --format mcap --log-layout samples|blocks [--out PATH]``.

Writes the log's raw CAN frames through python-can's writers (BLF and ASC open in CANalyzer,
CANoe, SavvyCAN; all three read back with ``can.LogReader``), or with ``--samples`` (csv only)
the samples, one column per scalar field; or the whole log in the other message layout
(:mod:`dob_hil.log.convert`). Default output beside the log: ``<stem>.blf``, ``<stem>.asc``,
``<stem>-frames.csv``, ``<stem>-samples.csv``, ``<stem>-<layout>.mcap``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from dob_hil.errors import ConfigError


def main(args: argparse.Namespace) -> int:
    """Export streamed (:mod:`dob_hil.analysis.export`): bounded memory for a log of any length."""
    from dob_hil.analysis.export import default_export_path, export_log_frames, write_log_samples_csv
    from dob_hil.log.stream import return_large_buffers_to_the_os

    if args.samples and args.format != "csv":
        raise ConfigError("--samples", f"samples are exported as csv only, not {args.format}")
    if (args.format == "mcap") != (args.log_layout is not None):
        raise ConfigError("--log-layout", "give it with --format mcap, and only then (the layout to write)")
    log_path = Path(args.log)
    if args.format == "mcap":
        return _convert(log_path, Path(args.out) if args.out else None, args.log_layout)
    out = Path(args.out) if args.out else default_export_path(log_path, args.format, args.samples)
    if out.resolve() == log_path.resolve():
        raise ConfigError("--out", f"{out} is the log itself")
    return_large_buffers_to_the_os()
    if args.samples:
        n, warnings = write_log_samples_csv(log_path, out)
        _warn(log_path, warnings)
        print(f"{out}: {n} samples")
        return 0
    result = export_log_frames(log_path, out, args.format)
    if result.out_of_order:
        result.warnings.append(
            f"{result.out_of_order} frames earlier than their channel's previous one, written in file order"
        )
    _warn(log_path, result.warnings)
    dropped = f", {result.echoes} received copies of own frames left out" if result.echoes else ""
    print(f"{out}: {result.frames} frames ({args.format}){dropped}")
    return 0


def _convert(log_path: Path, out: Path | None, layout: str) -> int:
    from dob_hil.log.convert import convert_layout

    out = out or log_path.with_name(f"{log_path.stem}-{layout}.mcap")
    if out.resolve() == log_path.resolve():
        raise ConfigError("--out", f"{out} is the log itself")
    if out.is_dir() or not out.parent.is_dir():
        raise ConfigError("--out", f"{out}: not a file in an existing folder")
    result = convert_layout(log_path, out, layout)
    _warn(log_path, result.warnings)
    print(f"{out}: {result.records} records, {layout} layout ({out.stat().st_size} bytes)")
    return 0


def _warn(log_path: Path, warnings: list[str]) -> None:
    for warning in warnings:
        print(f"dob-hil export: warning: {log_path}: {warning}", file=sys.stderr)
