"""``dob-hil analyze LOG.mcap [LOG2.mcap ...]``: metrics table (or JSON) and PNG plots.

Text output: one table, one column per log, then notes; warnings (what a damaged log lost, what
a log lacks) go to stderr. ``--json`` prints only JSON on stdout: a list with one object per log,
in the order given, with the keys documented in :mod:`dob_hil.analysis.metrics` plus ``plots``
(the PNG paths written, the same list for every log; empty with ``--no-plots``). Numbers that
the log cannot give are ``null``. Plots go to ``--plots DIR``, by default to a folder beside the
first log: ``<stem>-plots/`` (one log) or ``<stem1>-vs-<stem2>-plots/`` (several, overlaid).

A log of more than ``STREAM_ABOVE_SAMPLES`` samples is analysed streamed, in memory independent of
its length (:mod:`dob_hil.analysis.streamed`), and its plots show a window of it read through the
chunk index (:mod:`dob_hil.analysis.plot_window`): its first ``STREAM_ABOVE_SAMPLES`` samples, or
``--plot-window START:END`` seconds. Shorter logs are read whole and plotted whole unless
``--plot-window`` is given.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from dob_hil.errors import ConfigError


def default_plots_dir(paths: list[Path]) -> Path:
    first = paths[0]
    if len(paths) == 1:
        return first.with_name(f"{first.stem}-plots")
    if len(paths) == 2:
        return first.with_name(f"{first.stem}-vs-{paths[1].stem}-plots")
    return first.with_name(f"{first.stem}-and-{len(paths) - 1}-more-plots")


def _clean(value: Any) -> Any:
    """NaN/inf -> None, recursively, so the JSON is strict."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    return value


# Logs of more samples than this are analysed streamed (bounded memory, dob_hil.analysis.streamed)
# when no plots are asked for; shorter ones are read whole (the figures are the same; sums of
# squares may differ in the last bits between the two paths).
STREAM_ABOVE_SAMPLES = 100_000


def _x_ref_blocks(log: Any) -> Iterator[Any]:
    if len(log.data.samples):
        yield log.data.samples["x_ref"]
        return
    from dob_hil.analysis.streamed import x_ref_blocks

    yield from x_ref_blocks(log.path)


def same_prefix(a: Iterator[Any], b: Iterator[Any]) -> bool:
    """Whether two streams of arrays (blocks of rows) agree on the rows both hold (numpy's
    ``array_equal`` of the common prefix: NaN never equals)."""
    import numpy as np

    left = next(a, None)
    right = next(b, None)
    while left is not None and right is not None:
        n = min(len(left), len(right))
        if not np.array_equal(left[:n], right[:n]):
            return False
        left = left[n:] if len(left) > n else next(a, None)
        right = right[n:] if len(right) > n else next(b, None)
    return True


def comparison_warnings(logs: list[Any]) -> list[str]:
    """What makes logs compared side by side not like for like: different plants, periods,
    output units or references (the plots overlay them on one axis)."""
    import numpy as np

    out: list[str] = []
    if len(logs) < 2:
        return out
    first = logs[0]
    for log in logs[1:]:
        if log.period_ns != first.period_ns:
            out.append(
                f"{log.path.name} has a period of {log.period_ns / 1000:g} us, {first.path.name} "
                f"{first.period_ns / 1000:g} us: the logs are compared on different time grids"
            )
        a, b = first.design, log.design
        if a is not None and b is not None:
            if (
                a.A.shape != b.A.shape
                or a.B.shape != b.B.shape
                or not (
                    np.array_equal(a.A, b.A)
                    and np.array_equal(a.B, b.B)
                    and np.array_equal(a.C_cont, b.C_cont)
                )
            ):
                out.append(
                    f"{log.path.name} and {first.path.name} are runs of different plants (A, B or C differ)"
                )
            elif a.output_unit != b.output_unit:
                out.append(
                    f"{log.path.name} measures in {b.output_unit!r}, {first.path.name} in {a.output_unit!r}"
                )
        if not same_prefix(_x_ref_blocks(first), _x_ref_blocks(log)):
            out.append(f"{log.path.name} and {first.path.name} follow different references")
    return out


def indexed_samples(path: Path) -> int:
    """How many samples the log's message indexes count (0 for a file that is no log: the
    reading proper then reports it)."""
    from dob_hil.errors import DobHilError
    from dob_hil.log.schemas import TOPIC_SAMPLE
    from dob_hil.log.stream import open_stream

    try:
        with open_stream(path, {TOPIC_SAMPLE: ("seq",)}, events=False) as stream:
            return stream.counts.get(TOPIC_SAMPLE, 0)
    except DobHilError:
        return 0


def analyze_logs(
    paths: list[Path],
    *,
    from_s: float,
    plots_dir: Path | None,
    as_json: bool,
    plots: bool = True,
    table_path: Path | None = None,
    plot_window_s: tuple[float, float] | None = None,
) -> list[dict[str, Any]]:
    """Read each log, compute its metrics over ``from_s`` .. end, print them (table or JSON on
    stdout, warnings on stderr), write the overlaid plots (unless ``plots`` is False) into
    ``plots_dir`` (None: :func:`default_plots_dir`), the table also into ``table_path`` if given,
    and return the metrics, one dict per log. ``plot_window_s`` (start, end) in seconds from each
    log's first sample limits the plots to that stretch (module docstring).
    Raises LogReadError for a file that is no log at all, ConfigError for a bad ``from_s`` or a
    window that holds no samples."""
    from dob_hil.analysis.loaded import ANALYSIS_FIELDS, load_log
    from dob_hil.analysis.metrics import compute_metrics
    from dob_hil.analysis.signals import derive_signals
    from dob_hil.analysis.table import format_table

    if not paths:
        raise ConfigError("logs", "give at least one MCAP log")
    if not (math.isfinite(from_s) and from_s >= 0.0):
        raise ConfigError("--from", f"must be a number of seconds >= 0, got {from_s}")
    paths = [Path(p) for p in paths]
    if plots:  # refused before any log is read
        from dob_hil.commands.paths import ensure_dir

        ensure_dir(plots_dir if plots_dir is not None else default_plots_dir(paths), "--plots")
    logs: list[Any] = []
    results: list[dict[str, Any]] = []
    plotted: list[Any] = []  # (log, signals) of the stretch each log's plots show
    windows: list[str] = []
    for p in paths:
        if indexed_samples(p) > STREAM_ABOVE_SAMPLES:
            from dob_hil.analysis.streamed import streamed_metrics, survey
            from dob_hil.log.stream import return_large_buffers_to_the_os

            return_large_buffers_to_the_os()
            log, sv = survey(p, from_s)
            metrics = streamed_metrics(log, sv)
            if plots and sv.n:
                from dob_hil.analysis.plot_window import window_of_long_log

                window = plot_window_s
                if window is None:
                    window = (0.0, STREAM_ABOVE_SAMPLES * (log.period_ns or 0) * 1e-9)
                plotted.append(window_of_long_log(p, sv.t0, sv.last["time_ns"], log.period_ns, window))
                span_s = (sv.last["time_ns"] - sv.t0) * 1e-9
                windows.append(f"{p.name}: {window[0]:g}-{window[1]:g} s of 0-{span_s:g} s")
        else:
            log = load_log(p, fields=ANALYSIS_FIELDS)
            sig = derive_signals(log)
            metrics = compute_metrics(log, from_s, sig)
            if plots and plot_window_s is not None:
                from dob_hil.analysis.plot_window import window_of_loaded_log

                plotted.append(window_of_loaded_log(log, plot_window_s))
            elif plots:
                plotted.append((log, sig))
            else:  # nothing else needs the arrays: let them go before the next log
                for name in ("samples", "frames", "truth", "fd_frames"):
                    setattr(log.data, name, getattr(log.data, name)[:0].copy())
                del sig
        logs.append(log)
        results.append(_clean(metrics))
    for warning in comparison_warnings(logs):
        print(f"dob-hil analyze: warning: {warning}", file=sys.stderr)
    for log, metrics in zip(logs, results, strict=True):
        for warning in metrics["warnings"]:
            print(f"dob-hil analyze: warning: {log.path}: {warning}", file=sys.stderr)
    written: list[Path] = []
    if plots:
        from dob_hil.analysis.plots import PlotInput, write_plots

        out_dir = plots_dir if plots_dir is not None else default_plots_dir(paths)
        written = write_plots([PlotInput(log, sig) for log, sig in plotted], out_dir, from_s=from_s)
    for metrics in results:
        metrics["plots"] = [str(p) for p in written]
        metrics["plot_window_s"] = None if plot_window_s is None else list(plot_window_s)
    if as_json:
        print(json.dumps(results, indent=1, allow_nan=False))
    units = {log.design.output_unit for log in logs if log.design is not None}
    table = format_table(results, [log.label for log in logs], units.pop() if len(units) == 1 else "")
    if table_path is not None:  # the comparison table as a file too (dob-hil demo)
        table_path.write_text(table + "\n", encoding="utf-8")
    if not as_json:
        print(table)
        if written:
            print(f"plots: {len(written)} PNG files in {written[0].parent}")
        if windows and plot_window_s is None:
            shown = "; ".join(windows)
            print(f"plots of long logs show a window (--plot-window START:END chooses it): {shown}")
    return results


def _plot_window(args: argparse.Namespace) -> tuple[float, float] | None:
    text = getattr(args, "plot_window", None)
    if text is None:
        return None
    if args.no_plots:
        raise ConfigError("--plot-window", "chooses what the plots show, and --no-plots asks for no plots")
    from dob_hil.analysis.plot_window import parse_plot_window

    return parse_plot_window(text)


def main(args: argparse.Namespace) -> int:
    analyze_logs(
        [Path(p) for p in args.logs],
        from_s=args.from_s,
        plots_dir=Path(args.plots) if args.plots else None,
        as_json=args.json,
        plots=not args.no_plots,
        plot_window_s=_plot_window(args),
    )
    return 0
