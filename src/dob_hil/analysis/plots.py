"""PNG plots of one or more logs (matplotlib, Agg backend, imported here only).

Several logs (e.g. the same scenario with the DOB on and off) are overlaid, one colour per log:

* ``output.png``: reference, plant output (true where the log has ground truth, else measured) and
  model output (:mod:`dob_hil.analysis.model`), and plant minus model (the paper's Figures 6/8);
* ``disturbance.png``: injected disturbance w and its estimate -u_dist (Figures 7/9);
* ``sensitivity.png``: |S| and |T| at the plant output of each logged design (Figure 5);
* ``tracking_error.png``: reference minus plant output, with the start of the metrics window;
* ``command.png``: commanded and applied current with the current limit;
* ``timing.png``: histograms of the feedback-to-command latency and the period jitter.

Long series are decimated (min/max per bucket, :mod:`dob_hil.analysis.downsample`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from dob_hil.analysis.downsample import envelope
from dob_hil.analysis.loaded import LoadedLog
from dob_hil.analysis.model import nominal_output
from dob_hil.analysis.signals import Signals
from dob_hil.design import sensitivity_response
from dob_hil.design.linalg import max_singular_value

FloatArray = npt.NDArray[np.float64]
DPI = 110
FIGSIZE = (9.0, 5.0)
HIST_BINS = 80


@dataclass(frozen=True)
class PlotInput:
    log: LoadedLog
    signals: Signals


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _db(x: Any) -> Any:
    return 20.0 * np.log10(np.maximum(np.asarray(x, dtype=np.float64), 1e-300))


def _line(ax: Any, t: FloatArray, y: FloatArray, **kwargs: Any) -> None:
    td, yd = envelope(t, y)
    ax.plot(td, yd, **kwargs)


def _unit(log: LoadedLog) -> tuple[str, str]:
    if log.design is not None:
        return log.design.output_unit, log.design.input_unit
    return "unit", "A"


def _model_outputs(inputs: list[PlotInput]) -> list[FloatArray | None]:
    """Model output per log; logs with the same design, reference and limit share one simulation."""
    done: list[tuple[PlotInput, FloatArray]] = []
    out: list[FloatArray | None] = []
    for item in inputs:
        log = item.log
        if log.design is None or len(log.data.samples) == 0:
            out.append(None)
            continue
        x_ref = np.asarray(log.data.samples["x_ref"], dtype=np.float64)
        x0 = np.asarray(log.data.samples["x_bar"][0], dtype=np.float64)
        reuse = None
        for other, y in done:
            o = other.log
            if (
                o.design == log.design
                and o.current_limit_A == log.current_limit_A
                and np.array_equal(o.data.samples["x_ref"], log.data.samples["x_ref"])
                and np.array_equal(o.data.samples["x_bar"][0], x0)
            ):
                reuse = y
                break
        if reuse is None:
            # the DOB setting does not change the nominal loop (module docstring of model)
            reuse = nominal_output(
                log.design, x_ref, dob_enabled=log.dob_enabled, current_limit_A=log.current_limit_A, x0=x0
            )
            done.append((item, reuse))
        out.append(reuse)
    return out


def _plot_output(plt: Any, inputs: list[PlotInput], models: list[FloatArray | None], out: Path) -> Path:
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(9.0, 7.0), sharex=True, height_ratios=(2, 1))
    y_unit = _unit(inputs[0].log)[0]
    first = inputs[0].signals
    _line(ax, first.t_s, first.y_ref[:, 0], color="k", lw=1.0, ls=":", label="reference")
    shown_models: list[int] = []
    for i, (item, model) in enumerate(zip(inputs, models, strict=True)):
        sig, color = item.signals, f"C{i}"
        truth = sig.has_truth.any()
        y = sig.y_true if truth else sig.y_meas
        _line(
            ax,
            sig.t_s,
            y[:, 0],
            color=color,
            lw=1.2,
            label=f"plant output{'' if truth else ' (measured)'}: {item.log.label}",
        )
        if model is None:
            continue
        if not any(models[j] is model for j in shown_models):
            _line(
                ax,
                sig.t_s,
                model[:, 0],
                color="0.4",
                lw=1.0,
                ls="--",
                label="model output" if not shown_models else f"model output ({item.log.label})",
            )
            shown_models.append(i)
        _line(ax2, sig.t_s, y[:, 0] - model[:, 0], color=color, lw=1.0, label=item.log.label)
    ax.set(ylabel=f"output [{y_unit}]", title=f"{inputs[0].log.scenario}: plant output vs model output")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    ax2.set(xlabel="time [s]", ylabel=f"plant - model [{y_unit}]")
    ax2.grid(True, alpha=0.3)
    fig.savefig(out, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return out


def _plot_disturbance(plt: Any, inputs: list[PlotInput], out: Path) -> Path:
    fig, ax = plt.subplots(figsize=FIGSIZE)
    u_unit = _unit(inputs[0].log)[1]
    shown_w = False
    for i, item in enumerate(inputs):
        sig, color = item.signals, f"C{i}"
        if sig.has_truth.any() and not shown_w:
            _line(ax, sig.t_s, sig.w_A[:, 0], color="k", lw=1.2, label="disturbance w (injected)")
            shown_w = True
        u_dist = np.asarray(item.log.data.samples["u_dist"][:, 0], dtype=np.float64)
        _line(ax, sig.t_s, -u_dist, color=color, lw=1.0, label=f"estimate -u_dist: {item.log.label}")
    ax.set(
        xlabel="time [s]",
        ylabel=f"current [{u_unit}]",
        title=f"{inputs[0].log.scenario}: disturbance and its estimate",
    )
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(out, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return out


def _plot_sensitivity(plt: Any, inputs: list[PlotInput], out: Path) -> Path | None:
    curves: list[tuple[Any, bool, str]] = []
    for item in inputs:
        d = item.log.design
        if d is None:
            continue
        if any(d == other and item.log.dob_enabled == on for other, on, _ in curves):
            continue
        curves.append((d, item.log.dob_enabled, item.log.label))
    if not curves:
        return None
    fig, ax = plt.subplots(figsize=FIGSIZE)
    for i, (design, on, label) in enumerate(curves):
        nyquist_hz = 0.5e9 / design.period_ns
        f_hz = np.logspace(np.log10(nyquist_hz) - 4.0, np.log10(nyquist_hz), 800)
        S, T = sensitivity_response(design, 2.0 * np.pi * f_hz, on)
        ax.semilogx(f_hz, _db(max_singular_value(S)), color=f"C{i}", ls="-", label=f"S: {label}")
        ax.semilogx(f_hz, _db(max_singular_value(T)), color=f"C{i}", ls="--", label=f"T: {label}")
    ax.set(
        xlabel="frequency [Hz]",
        ylabel="magnitude [dB]",
        title=f"{inputs[0].log.scenario}: sensitivity S and complementary sensitivity T at the plant output",
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(out, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return out


def _plot_tracking(plt: Any, inputs: list[PlotInput], from_s: float, out: Path) -> Path:
    fig, ax = plt.subplots(figsize=FIGSIZE)
    for i, item in enumerate(inputs):
        sig = item.signals
        truth = sig.has_truth.any()
        e = sig.y_ref[:, 0] - (sig.y_true if truth else sig.y_meas)[:, 0]
        _line(
            ax,
            sig.t_s,
            e,
            color=f"C{i}",
            lw=1.0,
            label=f"{item.log.label}{'' if truth else ' (vs measured)'}",
        )
    ax.axvline(from_s, color="0.5", ls=":", lw=1.0, label=f"metrics window from {from_s:g} s")
    ax.set(
        xlabel="time [s]",
        ylabel=f"reference - output [{_unit(inputs[0].log)[0]}]",
        title=f"{inputs[0].log.scenario}: tracking error",
    )
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(out, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return out


def _plot_command(plt: Any, inputs: list[PlotInput], out: Path) -> Path:
    fig, ax = plt.subplots(figsize=FIGSIZE)
    limits: set[float] = set()
    for i, item in enumerate(inputs):
        s, t = item.log.data.samples, item.signals.t_s
        _line(
            ax,
            t,
            np.asarray(s["u_cmd_a"][:, 0], dtype=np.float64),
            color=f"C{i}",
            lw=0.8,
            alpha=0.5,
            label=f"commanded: {item.log.label}",
        )
        _line(
            ax,
            t,
            np.asarray(s["u_applied_a"][:, 0], dtype=np.float64),
            color=f"C{i}",
            lw=1.2,
            label=f"applied: {item.log.label}",
        )
        if item.log.current_limit_A is not None:
            limits.add(item.log.current_limit_A)
    for limit in sorted(limits):
        ax.axhline(limit, color="r", ls="--", lw=0.8, label=f"limit +-{limit:g}")
        ax.axhline(-limit, color="r", ls="--", lw=0.8)
    if limits:  # the commanded current can be far beyond the limit: keep the applied range readable
        top = 3.0 * max(limits)
        lo, hi = ax.get_ylim()
        ax.set_ylim(max(lo, -top), min(hi, top))
    ax.set(
        xlabel="time [s]",
        ylabel=f"current [{_unit(inputs[0].log)[1]}]",
        title=f"{inputs[0].log.scenario}: current command and saturation limits",
    )
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(out, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return out


def _plot_timing(plt: Any, inputs: list[PlotInput], out: Path) -> Path:
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11.0, 4.5))
    for i, item in enumerate(inputs):
        s, fb = item.log.data.samples, item.signals.has_feedback
        rx = s["rx_time_ns"].astype(np.int64)
        tx = s["tx_time_ns"].astype(np.int64)
        latency_us = (tx - rx)[fb & (tx > 0)] * 1e-3
        pair = fb[1:] & fb[:-1] & (np.diff(s["seq"].astype(np.int64)) == 1)
        jitter_us = np.abs(np.diff(rx) - item.log.period_ns)[pair] * 1e-3
        for ax, values in ((ax1, latency_us), (ax2, jitter_us)):
            if len(values):
                ax.hist(values, bins=HIST_BINS, color=f"C{i}", alpha=0.5, log=True, label=item.log.label)
    ax1.set(xlabel="feedback receive -> command send [us]", ylabel="samples", title="latency")
    ax2.set(xlabel="|receive interval - period| [us]", ylabel="samples", title="period jitter")
    for ax in (ax1, ax2):
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    if any(item.log.mode == "lockstep" for item in inputs):
        fig.suptitle("lockstep: host wall-clock times of a simulation faster than real time", fontsize=9)
    fig.savefig(out, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return out


def write_plots(inputs: list[PlotInput], out_dir: Path, *, from_s: float) -> list[Path]:
    """Write the PNGs of the module docstring into ``out_dir``; returns their paths."""
    inputs = [item for item in inputs if len(item.log.data.samples)]
    if not inputs:
        return []
    plt = _pyplot()
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [
        _plot_output(plt, inputs, _model_outputs(inputs), out_dir / "output.png"),
        _plot_disturbance(plt, inputs, out_dir / "disturbance.png"),
    ]
    sens = _plot_sensitivity(plt, inputs, out_dir / "sensitivity.png")
    if sens is not None:
        paths.append(sens)
    paths.append(_plot_tracking(plt, inputs, from_s, out_dir / "tracking_error.png"))
    paths.append(_plot_command(plt, inputs, out_dir / "command.png"))
    paths.append(_plot_timing(plt, inputs, out_dir / "timing.png"))
    return paths
