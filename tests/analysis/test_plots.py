"""Every plot of the demo and of analyze: rendered, with labels, units and legends, and no legend
covering the data it describes (checked in display coordinates, as matplotlib draws them)."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dob_hil import cli
from dob_hil.analysis import plots
from dob_hil.analysis.loaded import load_log
from dob_hil.analysis.signals import derive_signals

UNIT = re.compile(r"\[[^\]]+\]")


def _inputs(paths: list[Path], **log_changes: Any) -> list[plots.PlotInput]:
    out = []
    for path in paths:
        log = load_log(path)
        if log_changes:
            log = dataclasses.replace(log, **log_changes)
        out.append(plots.PlotInput(log, derive_signals(log)))
    return out


def _legends(fig: Any) -> list[Any]:
    return [leg for leg in [*(ax.get_legend() for ax in fig.axes), *fig.legends] if leg is not None]


def check_figure(name: str, fig: Any) -> None:
    """Labels with units on every data axes, a title, a legend, and no legend over any line."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    data_axes = [ax for ax in fig.axes if ax.get_lines() or ax.patches]
    assert data_axes, name
    assert any(ax.get_title() for ax in fig.axes) or fig._suptitle is not None, name
    for ax in data_axes:
        assert (ax.get_ylabel() and UNIT.search(ax.get_ylabel())) or ax.get_ylabel() == "samples", (name, ax)
        if ax.get_xlabel() or not ax.get_shared_x_axes().get_siblings(ax)[1:]:
            assert UNIT.search(ax.get_xlabel()), (name, ax.get_xlabel())
    legends = _legends(fig)
    assert legends, f"{name}: no legend"
    for leg in legends:
        assert [t.get_text() for t in leg.get_texts()], name
        box = leg.get_window_extent(renderer)
        for ax in data_axes:
            for line in ax.get_lines():
                xy = line.get_transform().transform(np.asarray(line.get_xydata(), dtype=np.float64))
                xy = xy[np.all(np.isfinite(xy), axis=1)]
                inside = (xy[:, 0] > box.x0) & (xy[:, 0] < box.x1) & (xy[:, 1] > box.y0) & (xy[:, 1] < box.y1)
                assert not inside.any(), f"{name}: the legend covers {line.get_label()!r}"


@pytest.mark.parametrize("scenario", ["paper-step", "paper-sine"])
def test_every_analyze_plot_is_labelled_and_uncovered(
    scenario: str, runs: dict[tuple[str, bool], Path], figures: dict[str, Any], tmp_path: Path
) -> None:
    paths = [runs[(scenario, True)], runs[(scenario, False)]]
    written = plots.write_plots(_inputs(paths), tmp_path, from_s=0.1)
    names = {p.name for p in written}
    assert names == {"output.png", "disturbance.png", "sensitivity.png", "tracking_error.png", "command.png"}
    for name, fig in figures.items():
        check_figure(name, fig)
    # real-time logs also get their timing (lockstep timing is not real time: no plot)
    figures.clear()
    written = plots.write_plots(_inputs(paths, mode="realtime"), tmp_path / "rt", from_s=0.1)
    assert "timing.png" in {p.name for p in written}
    check_figure("timing.png", figures["timing.png"])


def test_the_output_plot_zooms_on_the_step(
    runs: dict[tuple[str, bool], Path], figures: dict[str, Any], tmp_path: Path
) -> None:
    plots.write_plots(_inputs([runs[("paper-step", True)]]), tmp_path, from_s=0.1)
    fig = figures["output.png"]
    zoom = [ax for ax in fig.axes if "step transient" in ax.get_title()]
    assert len(zoom) == 1
    lo, hi = zoom[0].get_xlim()
    assert 0.005 < hi - lo < 0.2  # tens of ms of a 0.3 s run
    labels = [t.get_text() for leg in _legends(fig) for t in leg.get_texts()]
    assert any(label.startswith("model output") and "(DOB on)" in label for label in labels)


def test_disturbance_plot_has_no_estimate_without_the_dob_and_states_the_gain(
    runs: dict[tuple[str, bool], Path], figures: dict[str, Any], tmp_path: Path
) -> None:
    paths = [runs[("paper-step", True)], runs[("paper-step", False)]]
    plots.write_plots(_inputs(paths), tmp_path, from_s=0.1)
    fig = figures["disturbance.png"]
    lines = [line.get_label() for line in fig.axes[0].get_lines() if len(line.get_xdata())]
    assert not any("estimate" in label and "DOB off" in label for label in lines)
    notes = [line.get_label() for line in fig.axes[0].get_lines() if not len(line.get_xdata())]
    assert any("DOB off, no estimate" in note for note in notes)
    assert any(re.search(r"gain 0\.\d\d x w", label) for label in lines), lines


def test_the_command_plot_clips_nothing(
    runs: dict[tuple[str, bool], Path], figures: dict[str, Any], tmp_path: Path
) -> None:
    inputs = _inputs([runs[("paper-step", True)], runs[("paper-step", False)]])
    plots.write_plots(inputs, tmp_path, from_s=0.1)
    fig = figures["command.png"]
    assert len(fig.axes) == 2  # one panel per run: neither hides the other
    for ax, item in zip(fig.axes, inputs, strict=True):
        lo, hi = ax.get_ylim()
        cmd = np.asarray(item.log.data.samples["u_cmd_a"][:, 0])
        assert lo <= cmd.min() and cmd.max() <= hi
        labels = [line.get_label() for line in ax.get_lines()]
        assert any("commanded" in s for s in labels) and any("applied" in s for s in labels)
        assert any(re.search(r"limit \+-0\.7 A", s) for s in labels)


def test_mathtext_in_a_logged_unit_is_shown_literally(
    runs: dict[tuple[str, bool], Path], figures: dict[str, Any], tmp_path: Path
) -> None:
    log = load_log(runs[("paper-step", True)])
    assert log.design is not None
    design = dataclasses.replace(log.design, output_unit="$\\frac{$", name="$x$")
    log = dataclasses.replace(log, design=design)
    written = plots.write_plots([plots.PlotInput(log, derive_signals(log))], tmp_path, from_s=0.1)
    assert written and all(p.stat().st_size > 0 for p in written)
    assert "\\$\\\\frac{\\$" in figures["output.png"].axes[0].get_ylabel()


def test_the_demo_writes_every_file_it_promises(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["demo", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    table = tmp_path / "demo-paper-step-comparison.txt"
    assert table.is_file() and "tracking error rms" in table.read_text()
    assert str(table) in out
    pngs = {p.name for p in (tmp_path / "demo-paper-step-plots").glob("*.png")}
    assert pngs == {"output.png", "disturbance.png", "sensitivity.png", "tracking_error.png", "command.png"}
    assert any((tmp_path / "demo-paper-step-design").glob("*.png"))


def test_comparing_different_plants_or_periods_warns(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    step, sine = runs[("paper-step", True)], runs[("paper-sine", True)]
    assert cli.main(["analyze", str(step), str(sine), "--no-plots"]) == 0
    err = capsys.readouterr().err
    assert "follow different references" in err
    from dob_hil.commands.analyze import comparison_warnings

    a, b = load_log(step), load_log(sine)
    b = dataclasses.replace(b, period_ns=b.period_ns * 2)
    assert any("different time grids" in w for w in comparison_warnings([a, b]))
