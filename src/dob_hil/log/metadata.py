"""Builders of the log's metadata records ("versions", "run", "log_format").

MCAP metadata maps strings to strings; numbers and lists are written as JSON text.
"""

from __future__ import annotations

import json
import platform
import sys
import time
from importlib import metadata as importlib_metadata

import dob_hil
from dob_hil.log.schemas import LogLayout, channel_specs

LOG_FORMAT_NAME = "dob_hil.log"
LOG_FORMAT_VERSION = "2"  # 2: events are ros2msg/cdr dob_hil/msg/Event; sequence numbers set at the source


def _version(distribution: str) -> str:
    try:
        return importlib_metadata.version(distribution)
    except importlib_metadata.PackageNotFoundError:
        return "not installed"


def versions_metadata() -> dict[str, str]:
    """The "versions" record: dob_hil, python, numpy, python-can, mcap, zstandard, platform."""
    return {
        "dob_hil": dob_hil.__version__,
        "python": sys.version.split()[0],
        "numpy": _version("numpy"),
        "python-can": _version("python-can"),
        "mcap": _version("mcap"),
        "zstandard": _version("zstandard"),
        "platform": platform.platform(),
    }


def run_metadata(
    *,
    mode: str,
    bus: str,
    period_ns: int,
    layout: LogLayout,
    start_wall_time_ns: int | None = None,
    **extra: object,
) -> dict[str, str]:
    """The "run" record: mode (lockstep/realtime), bus, start wall time, period and dimensions."""
    start_ns = time.time_ns() if start_wall_time_ns is None else start_wall_time_ns
    data = {
        "mode": mode,
        "bus": bus,
        "start_wall_time_ns": str(start_ns),
        "start_wall_time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(start_ns / 1e9)),
        "period_ns": str(period_ns),
        **layout.as_metadata(),
    }
    for key, value in extra.items():
        data[key] = value if isinstance(value, str) else json.dumps(value, default=str)
    return data


def log_format_metadata(layout: LogLayout, message_layout: str = "samples") -> dict[str, str]:
    """The "log_format" record: enough to decode the data chunks even if the schemas were lost
    (``message_layout``: one message per record, or blocks of records)."""
    return {
        "format": LOG_FORMAT_NAME,
        "version": LOG_FORMAT_VERSION,
        **layout.as_metadata(),
        "message_layout": message_layout,
        "channels": json.dumps({str(spec.key): spec.topic for spec in channel_specs(layout)}),
    }
