"""``python -m firmware_sim.conformance``: see :mod:`firmware_sim.conformance`."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

from dob_hil.errors import DobHilError
from dob_hil.link.bus import open_bus
from dob_hil.link.protocol import NODE_ID_MAX, PROTOCOL_VERSION
from firmware_sim.conformance import KitOptions, RuleResult, run_conformance

PROG = "python -m firmware_sim.conformance"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description=f"Check a drive against the native protocol (version {PROTOCOL_VERSION}), "
        "rule by rule (docs/PROTOCOL.md).",
    )
    p.add_argument("-i", "--interface", help="python-can interface (socketcan, udp_multicast, ...)")
    p.add_argument("-c", "--channel", help="python-can channel")
    p.add_argument("-b", "--bitrate", type=int, help="bus bitrate in bit/s")
    p.add_argument("--node", type=int, default=1, help=f"the drive's node id, 0..{NODE_ID_MAX} (default 1)")
    p.add_argument(
        "--watchdog-periods", type=int, default=10, help="the drive's configured watchdog (default 10)"
    )
    p.add_argument(
        "--full-current",
        action="store_true",
        help="also run C1/C2, which command the drive's full current for a few periods",
    )
    p.add_argument(
        "--answer-timeout-ms",
        type=float,
        default=500.0,
        help="a HEARTBEAT answering a CONTROL must come within this (default 500)",
    )
    p.add_argument("--json", action="store_true", help="print the results as JSON")
    return p


def format_results(results: list[RuleResult]) -> str:
    lines = [f"{r.rule:<3} {r.status.upper():<4}  {r.title}" + (f"\n          {r.detail}" if r.detail else "")
             for r in results]  # fmt: skip
    failed = sum(r.status == "fail" for r in results)
    skipped = sum(r.status == "skip" for r in results)
    lines.append(f"{len(results) - failed - skipped} passed, {failed} failed, {skipped} skipped")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not 0 <= args.node <= NODE_ID_MAX:
        parser.error(f"--node must be 0..{NODE_ID_MAX}, got {args.node}")
    if not 1 <= args.watchdog_periods <= 1_000_000:
        parser.error(f"--watchdog-periods must be 1..1000000, got {args.watchdog_periods}")
    if not 0 < args.answer_timeout_ms <= 60_000:
        parser.error(f"--answer-timeout-ms must be in (0, 60000], got {args.answer_timeout_ms}")
    options = KitOptions(
        node_id=args.node,
        watchdog_periods=args.watchdog_periods,
        full_current=args.full_current,
        answer_timeout_s=args.answer_timeout_ms / 1000,
    )
    try:
        bus = open_bus(args.interface, args.channel, args.bitrate)
    except DobHilError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    try:
        results = run_conformance(bus, options)
    finally:
        bus.shutdown()
    if args.json:
        print(json.dumps({"protocol_version": PROTOCOL_VERSION, "node_id": args.node,
                          "results": [r.to_dict() for r in results]}, indent=2))  # fmt: skip
    else:
        print(format_results(results))
    return 1 if any(r.status == "fail" for r in results) else 0


if __name__ == "__main__":
    sys.exit(main())
