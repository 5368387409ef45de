"""``dob-hil demo``: the paper's example end to end on the embedded simulated drive.

Designs the controller (report and plots), runs the scenario in lockstep with and without the
disturbance observer, and analyses the two logs side by side: the metrics table (printed and
written to ``demo-<name>-comparison.txt``) and the plots (``demo-<name>-plots/``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from dob_hil.config import load_config
from dob_hil.scenarios import scenario_path


def main(args: argparse.Namespace) -> int:
    from dob_hil.commands.paths import ensure_dir
    from dob_hil.commands.run import format_summary
    from dob_hil.loop.session import RunOptions, run_session

    out = ensure_dir(Path(args.out), "--out")
    config = load_config(scenario_path(args.scenario))
    print(f"== design: {config.name}")
    from dob_hil.commands.design import write_design_outputs

    write_design_outputs(config, out / f"demo-{config.name}-design", quiet=False)

    logs: list[Path] = []
    for dob in (True, False):
        label = "dob" if dob else "nodob"
        path = out / f"demo-{config.name}-{label}.mcap"
        print(f"\n== run: {config.name}, DOB {'on' if dob else 'off'}")
        summary = run_session(config, RunOptions(dob_enabled=dob, log_path=path))
        print(format_summary(summary.to_dict()))
        if summary.exit_reason != "completed":
            return 1
        logs.append(path)

    print(f"\n== analysis: {logs[0].name} vs {logs[1].name}")
    from dob_hil.commands.analyze import analyze_logs

    table = out / f"demo-{config.name}-comparison.txt"
    analyze_logs(
        logs, from_s=0.1, plots_dir=out / f"demo-{config.name}-plots", as_json=False, table_path=table
    )
    print(f"comparison table: {table}")
    return 0
