"""``dob-hil design CONFIG``: design the controller, print the report, write the design JSON and plots."""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path
from typing import Any

from dob_hil.config import Config, load_config
from dob_hil.scenarios import resolve_config_path

DESIGN_FILE_NAME = "design.json"


def write_design_outputs(
    config: Config,
    out_dir: Path,
    *,
    quiet: bool = False,
    plots: bool = True,
    as_json: bool = False,
    optimize: bool = False,
) -> dict[str, Any]:
    """Design ``config`` (``optimize``: by the optimize method, with its trade-off curve), write
    ``out_dir/design.json`` and (``plots``) the PNGs, print the report (text, or JSON with
    ``as_json``; nothing with ``quiet``) and return the report dictionary.
    Raises DesignError/ConfigError for a design that must not run."""
    from dob_hil.design import design_with_diagnostics
    from dob_hil.design.analysis import analyze
    from dob_hil.design.report import format_report, gains_toml
    from dob_hil.design.robustness import DesignWarning
    from dob_hil.link.busload import refuse_overload
    from dob_hil.profiles import get_profile

    profile = get_profile(config.drive.profile)
    profile.check_period(config.plant.period_ns)
    if profile.input_delay_samples > config.plant.input_delay_samples:
        print(
            f"dob-hil design: warning: the {profile.name} profile adds {profile.input_delay_samples} "
            f"sample(s) of input delay, but plant.input_delay_samples = {config.plant.input_delay_samples} "
            "does not model it",
            file=sys.stderr,
        )
    load = refuse_overload(profile.bus_load(config))  # refuses a load above 100 %
    with warnings.catch_warnings():  # the report lists them (WARNINGS)
        warnings.simplefilter("ignore", DesignWarning)
        result = design_with_diagnostics(config, optimize=optimize)
    analysis = analyze(result, config)
    from dob_hil.commands.paths import ensure_dir

    ensure_dir(out_dir, "--out")
    design_path = out_dir / DESIGN_FILE_NAME
    result.design.save(design_path)
    files = [design_path]
    if plots:
        from dob_hil.design.plots import write_plots

        files += write_plots(analysis, out_dir)
        if result.optimized is not None:
            from dob_hil.design.plots import write_tradeoff_plot

            files.append(write_tradeoff_plot(config, result, out_dir))
    report = analysis.to_dict()
    report["files"] = [str(p) for p in files]
    report["bus_load"] = {
        "worst_case_fraction": load.fraction,
        "time_per_period_us": load.time_per_period_us,
        "bitrate_bps": load.bitrate_bps,
        "frame_bits": dict(load.frame_bits),
        "frames_per_period": dict(load.frames_per_period),
    }
    if as_json:
        print(json.dumps(report, indent=1, allow_nan=False))
    elif not quiet:
        print(format_report(report))
        if result.optimized is not None:
            print()
            print(gains_toml(result))
        print()
        print(load.breakdown())
    return report


def main(args: argparse.Namespace) -> int:
    config = load_config(resolve_config_path(args.config))
    out_dir = Path(args.out) if args.out else Path("logs") / f"design-{config.name}"
    write_design_outputs(
        config, out_dir, plots=not args.no_plots, as_json=args.json, optimize=getattr(args, "optimize", False)
    )
    return 0
