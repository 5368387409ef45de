"""``dob-hil doctor``: check the CAN interface and the host before a real-time run."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from dob_hil.errors import ConfigError

MARK = {"pass": "ok  ", "warn": "WARN", "fail": "FAIL", "skip": "skip"}


def _read(path: str | None, what: str) -> str | None:
    if path is None:
        return None
    try:
        return Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(what, f"cannot read {path}: {exc}") from None


def _python_can_config(args: argparse.Namespace) -> dict[str, Any]:
    """The bus python-can would open for these arguments (its config files and environment)."""
    import can

    given = {k: v for k, v in (("interface", args.interface), ("channel", args.channel)) if v is not None}
    try:
        return dict(can.util.load_config(config=given))
    except (can.CanInterfaceNotImplementedError, NotImplementedError, ValueError):
        return given


def main(args: argparse.Namespace) -> int:
    from dob_hil.doctor import BusTarget, run_doctor

    bitrate = args.bitrate
    if bitrate is None and args.config:
        from dob_hil.config import load_config
        from dob_hil.scenarios import resolve_config_path

        bitrate = load_config(resolve_config_path(args.config)).drive.bitrate_bps
    bus = _python_can_config(args)
    port = bus.get("port")
    if port is not None and not isinstance(port, int):
        raise ConfigError("port", f"udp_multicast port must be an integer, got {port!r}")
    target = BusTarget(
        interface=bus.get("interface"),
        channel=None if bus.get("channel") is None else str(bus["channel"]),
        bitrate_bps=bitrate,
        data_bitrate_bps=args.data_bitrate,
        port=port,
    )
    checks = run_doctor(
        target,
        ip_link_text=_read(args.ip_link_file, "--ip-link-file"),
        ethtool_text=_read(args.ethtool_file, "--ethtool-file"),
    )
    failed = any(c.status.value == "fail" for c in checks)
    if args.json:
        print(json.dumps({"target": vars(target), "checks": [c.to_dict() for c in checks], "ok": not failed},
                         indent=1))  # fmt: skip
    else:
        width = max(len(c.name) for c in checks)
        for c in checks:
            print(f"{MARK[c.status.value]}  {c.name:<{width}}  {c.detail}")
            if c.fix and c.status.value in ("warn", "fail"):
                print(f"      {'':<{width}}  fix: {c.fix}")
        print("doctor: " + ("FAILED: fix the FAIL lines before a real-time run" if failed else "no failures"),
              file=sys.stderr)  # fmt: skip
    return 1 if failed else 0
