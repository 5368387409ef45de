"""Shared helpers of the benchmarks: percentiles, repeats, and a uniform report."""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
from collections.abc import Sequence
from typing import Any


def percentiles(values: Sequence[float], qs: Sequence[float] = (50, 90, 99, 99.9)) -> dict[str, float]:
    """Nearest-rank percentiles plus max, of a non-empty sequence."""
    s = sorted(values)
    n = len(s)
    out = {f"p{q:g}": s[min(n - 1, max(0, round(q / 100 * n + 0.5) - 1))] for q in qs}
    out["max"] = s[-1]
    out["min"] = s[0]
    return out


def median(values: Sequence[float]) -> float:
    return float(statistics.median(values))


def parser(description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--smoke", action="store_true", help="a few seconds, for CI: no figures asserted")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    return p


def machine() -> dict[str, Any]:
    return {
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "loadavg": os.getloadavg() if hasattr(os, "getloadavg") else None,
    }


def report(name: str, result: dict[str, Any], as_json: bool) -> None:
    result = {"benchmark": name, "machine": machine(), **result}
    if as_json:
        print(json.dumps(result, indent=2))
        return
    print(f"== {name}")
    for key, value in result.items():
        if key in ("benchmark",):
            continue
        if isinstance(value, dict):
            inner = ", ".join(f"{k} {_fmt(v)}" for k, v in value.items())
            print(f"  {key}: {inner}")
        else:
            print(f"  {key}: {_fmt(value)}")


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)
