"""``dob-hil --help`` wall time beside ``python -c pass`` and ``import dob_hil.cli``, and what it imports.

Each command runs as a fresh process ``--runs`` times (interleaved, so all see the same machine
state); median and p90 of the wall time. Then ``dob-hil --help`` once under ``python -X
importtime``: the heavy modules it imports (none of numpy, scipy, can, mcap, matplotlib, control,
zstandard, cantools expected) and the costliest top-level imports.

Goal: ``dob-hil --help`` under 0.5 s, nothing heavy imported.

    .venv/bin/python benchmarks/bench_cli.py [--smoke] [--json] [--runs N]
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from _common import median, parser, percentiles, report

HEAVY = ("numpy", "scipy", "can", "mcap", "mcap_ros2", "matplotlib", "control", "zstandard", "cantools")
GOAL_S = 0.5
HELP_CODE = "import sys; from dob_hil.cli import main; sys.exit(main(sys.argv[1:]))"


def dob_hil_help() -> list[str]:
    """The installed console script if there is one (what a user runs), else the same via -c."""
    script = Path(os.path.normpath(sys.executable)).with_name("dob-hil")
    if script.exists():
        return [str(script), "--help"]
    return [sys.executable, "-c", HELP_CODE, "--help"]


def wall_s(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, check=False)
    elapsed = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)}: exit status {proc.returncode}: {proc.stderr.decode()[-500:]}")
    return elapsed


def import_profile() -> tuple[list[str], list[tuple[str, float]], int]:
    """Heavy top-level packages imported by ``dob-hil --help``, the 8 costliest imports, module count."""
    proc = subprocess.run(
        [sys.executable, "-X", "importtime", "-c", HELP_CODE, "--help"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        check=True,
    )
    modules: list[tuple[str, float]] = []
    for line in proc.stderr.splitlines():
        if not line.startswith("import time:") or "|" not in line or "self [us]" in line:
            continue
        _self_us, cumulative_us, name = (part.strip() for part in line[len("import time:") :].split("|"))
        modules.append((name, int(cumulative_us) / 1000))
    tops = {name.split(".")[0] for name, _ in modules}
    heavy = sorted(t for t in tops if t in HEAVY)
    top_level = [(name.strip(), ms) for name, ms in modules if not name.startswith(" ")]
    costliest = sorted(top_level, key=lambda m: -m[1])[:8]
    return heavy, costliest, len(modules)


def main() -> None:
    p = parser(__doc__ or "")
    p.add_argument("--runs", type=int, help="runs of each command (default 20, smoke 3)")
    args = p.parse_args()
    runs = args.runs or (3 if args.smoke else 20)
    commands = {
        "python -c pass": [sys.executable, "-c", "pass"],
        "python -c 'import dob_hil.cli'": [sys.executable, "-c", "import dob_hil.cli"],
        "dob-hil --help": dob_hil_help(),
    }
    times: dict[str, list[float]] = {name: [] for name in commands}
    for cmd in commands.values():  # warm the page cache once
        wall_s(cmd)
    for _ in range(runs):
        for name, cmd in commands.items():
            times[name].append(wall_s(cmd))
    heavy, costliest, n_modules = import_profile()
    result: dict[str, Any] = {"runs": runs, "command": " ".join(commands["dob-hil --help"])}
    for name, values in times.items():
        pct = percentiles(values, (50, 90))
        result[f"{name} (s)"] = {"median": round(median(values), 4), "p90": round(pct["p90"], 4),
                                 "max": round(pct["max"], 4)}  # fmt: skip
    help_median = median(times["dob-hil --help"])
    result["help_minus_python_s"] = round(help_median - median(times["python -c pass"]), 4)
    result["modules_imported_by_help"] = n_modules
    result["heavy_modules_imported"] = heavy or "none"
    result["costliest_imports_ms"] = {name: round(ms, 1) for name, ms in costliest}
    result["goal_met"] = help_median < GOAL_S and not heavy
    result["goal"] = "dob-hil --help under 0.5 s, none of numpy/scipy/can/mcap/matplotlib/control imported"
    report("dob-hil --help start-up", result, args.json)


if __name__ == "__main__":
    main()
