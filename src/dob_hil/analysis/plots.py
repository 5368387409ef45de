"""PNG plots of one or more logs (matplotlib, Agg backend, imported here only).

Several logs (e.g. the same scenario with the DOB on and off) are overlaid, one colour per log:

* ``output.png``: reference, plant output (true where the log has ground truth, else measured) and
  model output (:mod:`dob_hil.analysis.model`: the designed loop simulated without disturbance,
  noise or quantisation), a zoom on the step transient, and plant minus model (paper Figures 6/8);
* ``disturbance.png``: injected disturbance w and its estimate -u_dist with its gain (Figures 7/9);
  a run without the DOB has no estimate and gets none drawn;
* ``sensitivity.png``: |S| and |T| at the plant output of each logged design (Figure 5), with their
  peaks and the injected disturbance frequencies;
* ``tracking_error.png``: reference minus plant output, whole run and the metrics window;
* ``command.png``: commanded and applied current with the current limit, one panel per log, on a
  scale linear within the limit and logarithmic beyond (nothing clipped);
* ``timing.png``: histograms of the feedback-to-command latency and the period jitter of the
  real-time logs (a lockstep run's timing is not real time: no plot).

Line conventions (shared with ``dob-hil design``'s plots): S blue and T red, DOB on solid and DOB
off dashed; a log's colour is ``C<i>``. Legends sit outside the axes, so they never cover data.
Text that comes from a log (names, units) is shown literally (``$`` never starts mathtext).
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
S_COLOR, T_COLOR = "tab:blue", "tab:red"
RUN_STYLES = ("-", "--", ":", "-.")  # DOB on first: solid; DOB off: dashed
LEGEND_FONTSIZE = 8


@dataclass(frozen=True)
class PlotInput:
    log: LoadedLog
    signals: Signals


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def literal(text: str) -> str:
    """``text`` as matplotlib shows it literally: ``$`` escaped, so no mathtext is parsed."""
    return text.replace("\\", "\\\\").replace("$", r"\$")


def _db(x: Any) -> Any:
    return 20.0 * np.log10(np.maximum(np.asarray(x, dtype=np.float64), 1e-300))


def _line(ax: Any, t: FloatArray, y: FloatArray, **kwargs: Any) -> None:
    td, yd = envelope(t, y)
    ax.plot(td, yd, **kwargs)


def _unit(log: LoadedLog) -> tuple[str, str]:
    if log.design is not None:
        return literal(log.design.output_unit), literal(log.design.input_unit)
    return "unit", "A"


def _label(log: LoadedLog) -> str:
    return literal(log.label)


def axis_name(log: LoadedLog, kind: str, j: int) -> str:
    """``output 2 (p2)`` / ``input 1 (i1)``: 1-based, with the plant's name for it when the log
    has a design (shown literally)."""
    names: tuple[str, ...] = ()
    if log.design is not None:
        names = log.design.output_names if kind == "output" else log.design.input_names
    return f"{kind} {j + 1}" + (f" ({literal(names[j])})" if j < len(names) else "")


def _legend_right(ax: Any) -> Any:
    """The axes' legend to the right of the axes (outside the data area)."""
    return ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=LEGEND_FONTSIZE, frameon=False)


def _title(inputs: list[PlotInput], what: str) -> str:
    names: list[str] = []
    for item in inputs:
        if item.log.scenario not in names:
            names.append(item.log.scenario)
    return f"{literal(' vs '.join(names))}: {what}"


def _legend_below(fig: Any, ax: Any, ncol: int = 2) -> Any:
    """The axes' legend under the axes (outside the data area)."""
    handles, labels = ax.get_legend_handles_labels()
    if not handles:
        return None
    return ax.legend(
        handles,
        labels,
        loc="upper center",
        bbox_to_anchor=(0.5, -0.14),
        ncol=min(ncol, len(handles)),
        fontsize=LEGEND_FONTSIZE,
        frameon=False,
    )


def _save(plt: Any, fig: Any, out: Path) -> Path:
    fig.savefig(out, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return out


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


def step_window(t_s: FloatArray, y_ref: FloatArray, y: FloatArray) -> tuple[float, float] | None:
    """(start, end) of the step transient: from just before the step (the reference's first jump,
    or a run that starts away from its reference) to a few rise times after the output first
    reaches 90 % of it; None without a step."""
    if len(t_s) < 4:
        return None
    span = float(max(np.max(y_ref), np.max(y)) - min(np.min(y_ref), np.min(y)))
    if not span > 0:
        return None
    jumps = np.flatnonzero(np.abs(np.diff(y_ref)) > 0.2 * span)
    if abs(float(y_ref[0]) - float(y[0])) > 0.2 * span:
        k, before = 0, float(y[0])  # the run starts with the step
    elif len(jumps):
        k = int(jumps[0]) + 1
        before = float(y_ref[k - 1])
    else:
        return None
    after = float(y_ref[k])
    target = before + 0.9 * (after - before)
    reached = np.flatnonzero((y[k:] >= target) if after > before else (y[k:] <= target))
    dt = float(t_s[1] - t_s[0])
    total = float(t_s[-1] - t_s[0])
    rise_s = float(t_s[k + reached[0]] - t_s[k]) if len(reached) else 0.05 * total
    width = min(max(4.0 * rise_s, 20 * dt), 0.5 * total)
    start = max(float(t_s[0]), float(t_s[k]) - 0.1 * width)
    return start, start + width


def _plot_output(plt: Any, inputs: list[PlotInput], models: list[FloatArray | None], out: Path) -> Path:
    """One block of panels per output (plant output vs model with the step zoom, and plant minus
    model); a single-output plant gets one block, titled as before."""
    first = inputs[0].signals
    truth0 = first.has_truth.any()
    p = first.y_ref.shape[1]
    windows = [
        step_window(first.t_s, first.y_ref[:, j], (first.y_true if truth0 else first.y_meas)[:, j])
        for j in range(p)
    ]
    zoomed = any(w is not None for w in windows)
    fig = plt.figure(figsize=(11.0, 7.5 * p))
    grid = fig.add_gridspec(
        2 * p, 3 if zoomed else 1, height_ratios=(2, 1) * p, hspace=0.4 if p == 1 else 0.55, wspace=0.3
    )
    for j in range(p):
        ax = fig.add_subplot(grid[2 * j, :2] if zoomed else grid[2 * j, 0])
        zoom = fig.add_subplot(grid[2 * j, 2]) if windows[j] is not None else None
        ax2 = fig.add_subplot(grid[2 * j + 1, :2] if zoomed else grid[2 * j + 1, 0], sharex=ax)
        _draw_output(plt, inputs, models, j, (ax, zoom, ax2), windows[j])
    return _save(plt, fig, out)


def _draw_output(
    plt: Any,
    inputs: list[PlotInput],
    models: list[FloatArray | None],
    j: int,
    axes: tuple[Any, Any, Any],
    window: tuple[float, float] | None,
) -> None:
    """Output ``j``'s panels: ``ax`` (reference, plant, model), ``zoom`` (the step, or None) and
    ``ax2`` (plant minus model)."""
    ax, zoom, ax2 = axes
    several = inputs[0].signals.y_ref.shape[1] > 1
    which = f"{axis_name(inputs[0].log, 'output', j)}: " if several else ""
    y_unit = _unit(inputs[0].log)[0]
    refs: list[FloatArray] = []
    for i, (item, model) in enumerate(zip(inputs, models, strict=True)):
        sig, color = item.signals, f"C{i}"
        if j >= sig.y_ref.shape[1]:
            continue
        targets = [a for a in (ax, zoom) if a is not None]
        if not any(len(r) == len(sig.y_ref) and np.array_equal(r, sig.y_ref[:, j]) for r in refs):
            refs.append(sig.y_ref[:, j])
            ref_label = "reference" if i == 0 else f"reference: {_label(item.log)}"
            for a in targets:
                _line(a, sig.t_s, sig.y_ref[:, j], color="k", lw=1.0, ls=":", label=ref_label)
        truth = sig.has_truth.any()
        y = sig.y_true if truth else sig.y_meas
        for a in targets:
            _line(a, sig.t_s, y[:, j], color=color, lw=1.3,
                  label=f"plant output{'' if truth else ' (measured)'}: {_label(item.log)}")  # fmt: skip
        if model is None:
            continue
        shared = [k for k, m in enumerate(models) if m is model]
        if shared[0] == i:  # draw each distinct model once, saying which runs it belongs to
            runs = (
                ("both runs" if len(inputs) == 2 else "all runs")
                if len(shared) == len(inputs) > 1
                else ", ".join(_label(inputs[k].log) for k in shared)
            )
            for a in targets:
                _line(a, sig.t_s, model[:, j], color="0.35", lw=1.0, ls=(0, (5, 2 + 2 * i)),
                      label=f"model output (nominal loop, no disturbance): {runs}")  # fmt: skip
        _line(ax2, sig.t_s, y[:, j] - model[:, j], color=color, lw=1.0, label=_label(item.log))
    name = axis_name(inputs[0].log, "output", j) if several else "output"
    ax.set(ylabel=f"{name} [{y_unit}]", title=_title(inputs, f"{which}plant output vs model output"))
    ax.grid(True, alpha=0.3)
    ax.tick_params(labelbottom=True)
    ax.set_xlabel("time [s]")
    if zoom is not None and window is not None:
        zoom.set_xlim(*window)
        lo, hi = _visible_range(zoom, *window)
        zoom.set_ylim(lo, hi)
        zoom.set(xlabel="time [s]", ylabel=f"{name} [{y_unit}]",
                 title=f"{which}step transient ({1000 * (window[1] - window[0]):.0f} ms)")  # fmt: skip
        zoom.grid(True, alpha=0.3)
        zoom.xaxis.set_major_locator(plt.MaxNLocator(4))
        ax.axvspan(*window, color="0.85", alpha=0.5, lw=0, label="zoomed")
    ax2.set(
        xlabel="time [s]", ylabel=f"plant - model [{y_unit}]", title=f"{which}plant output minus model output"
    )
    ax2.grid(True, alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    # one legend for the block, beside the lower panel: the lower panel's colours are the runs above
    ax2.legend(handles, labels, loc="upper left", bbox_to_anchor=(1.03, 1.0), fontsize=LEGEND_FONTSIZE,
               frameon=False)  # fmt: skip


def _visible_range(ax: Any, t0: float, t1: float) -> tuple[float, float]:
    lo, hi = np.inf, -np.inf
    for line in ax.get_lines():
        x = np.asarray(line.get_xdata(), dtype=np.float64)
        y = np.asarray(line.get_ydata(), dtype=np.float64)
        sel = (x >= t0) & (x <= t1) & np.isfinite(y)
        if sel.any():
            lo, hi = min(lo, float(y[sel].min())), max(hi, float(y[sel].max()))
    if not np.isfinite(lo):
        return ax.get_ylim()  # type: ignore[no-any-return]
    pad = 0.05 * (hi - lo or 1.0)
    return lo - pad, hi + pad


def estimate_gain(w: FloatArray, estimate: FloatArray) -> float | None:
    """Least-squares gain g of ``estimate ~ g w`` (None without a disturbance)."""
    ok = np.isfinite(w) & np.isfinite(estimate)
    ww = float(np.dot(w[ok], w[ok]))
    if ww <= 0.0:
        return None
    return float(np.dot(w[ok], estimate[ok])) / ww


def _plot_disturbance(plt: Any, inputs: list[PlotInput], from_s: float, out: Path) -> Path:
    """One panel per plant input (legend below a single panel, beside each of several)."""
    m = inputs[0].signals.w_A.shape[1]
    fig, axes = plt.subplots(m, 1, figsize=FIGSIZE if m == 1 else (9.0, 3.6 * m), sharex=True, squeeze=False)
    u_unit = _unit(inputs[0].log)[1]
    for j, ax in enumerate(axes[:, 0]):
        _draw_disturbance(ax, inputs, from_s, j, several=m > 1)
        ax.set(ylabel=f"{axis_name(inputs[0].log, 'input', j) if m > 1 else 'current'} [{u_unit}]")
        ax.grid(True, alpha=0.3)
        if m == 1:
            _legend_below(fig, ax, ncol=2)
        else:
            _legend_right(ax)
    for ax in axes[:, 0]:
        ax.set_xlabel("time [s]")
        ax.tick_params(labelbottom=True)
    if m > 1:
        fig.subplots_adjust(hspace=0.45)
    return _save(plt, fig, out)


def _draw_disturbance(ax: Any, inputs: list[PlotInput], from_s: float, j: int, *, several: bool) -> None:
    """Input ``j``'s injected disturbance and each run's estimate -u_dist (with its gain)."""
    shown_w: list[FloatArray] = []
    notes: list[str] = []
    for i, item in enumerate(inputs):
        sig, color = item.signals, f"C{i}"
        if j >= sig.w_A.shape[1]:
            continue
        w = sig.w_A[:, j]
        if sig.has_truth.any() and not any(len(s) == len(w) and np.array_equal(s, w, equal_nan=True)
                                           for s in shown_w):  # fmt: skip
            label = "disturbance w (injected)" if not shown_w else f"disturbance w: {_label(item.log)}"
            _line(ax, sig.t_s, w, color="k", lw=1.4, ls=RUN_STYLES[len(shown_w) % 4], label=label)
            shown_w.append(w)
        if not item.log.dob_enabled:
            notes.append(f"{_label(item.log)}: DOB off, no estimate")
            continue
        estimate = -np.asarray(item.log.data.samples["u_dist"][:, j], dtype=np.float64)
        window = sig.t_s >= from_s
        gain = estimate_gain(w[window], estimate[window]) if sig.has_truth.any() else None
        gain_text = f", gain {gain:.2f} x w" if gain is not None else ""
        _line(ax, sig.t_s, estimate, color=color, lw=1.1,
              label=f"estimate -u_dist: {_label(item.log)}{gain_text}")  # fmt: skip
    for note in notes:
        ax.plot([], [], ls="none", label=note)
    which = f"{axis_name(inputs[0].log, 'input', j)}: " if several else ""
    ax.set_title(_title(inputs, f"{which}disturbance and its estimate"))


def _sine_frequencies(inputs: list[PlotInput]) -> list[float]:
    freqs: list[float] = []
    for item in inputs:
        if item.log.config is None:
            continue
        for d in item.log.config.sim.disturbances:
            if d.kind == "sine" and d.frequency_hz > 0 and d.frequency_hz not in freqs:
                freqs.append(d.frequency_hz)
    return sorted(freqs)


def _plot_sensitivity(plt: Any, inputs: list[PlotInput], out: Path) -> Path | None:
    curves: list[tuple[Any, bool, str]] = []
    for item in inputs:
        d = item.log.design
        if d is None:
            continue
        if any(d == other and item.log.dob_enabled == on for other, on, _ in curves):
            continue
        curves.append((d, item.log.dob_enabled, _label(item.log)))
    if not curves:
        return None
    fig, ax = plt.subplots(figsize=FIGSIZE)
    nyquist_hz = 0.5e9 / min(design.period_ns for design, _, _ in curves)
    for i, (design, on, label) in enumerate(curves):
        ny = 0.5e9 / design.period_ns
        # stop short of Nyquist, where the discrete loop's response bends sharply (no notch)
        f_hz = np.logspace(np.log10(ny) - 4.0, np.log10(0.97 * ny), 800)
        S, T = sensitivity_response(design, 2.0 * np.pi * f_hz, on)
        style = RUN_STYLES[i % len(RUN_STYLES)] if len(curves) > 2 else ("-" if on else "--")
        for name, resp, color in (("S", S, S_COLOR), ("T", T, T_COLOR)):
            mag = _db(max_singular_value(resp))
            k = int(np.argmax(mag))
            peaked = 0 < k < len(mag) - 1 and mag[k] > mag[0] + 0.05  # a resonance, not a plateau
            peak = f" (peak {mag[k]:.1f} dB at {f_hz[k]:.3g} Hz)" if peaked else ""
            ax.semilogx(f_hz, mag, color=color, ls=style, lw=1.3, label=f"{name}: {label}{peak}")
            if peaked:
                ax.plot(f_hz[k], mag[k], marker="o", ms=5, color=color, ls="none")
    for f in _sine_frequencies(inputs):
        ax.axvline(f, color="0.5", lw=0.8, ls="-.", label=f"disturbance {f:g} Hz")
    ax.axvline(nyquist_hz, color="k", lw=0.8, ls=":", label=f"Nyquist {nyquist_hz:.0f} Hz")
    ax.set(xlabel="frequency [Hz]", ylabel="magnitude [dB]",
           title=_title(inputs, "S and T at the plant output"))  # fmt: skip
    ax.grid(True, which="both", alpha=0.3)
    _legend_below(fig, ax, ncol=2)
    return _save(plt, fig, out)


def _plot_tracking(plt: Any, inputs: list[PlotInput], from_s: float, out: Path) -> Path:
    """Whole run and metrics window: stacked for one output, side by side per output for several."""
    p = inputs[0].signals.y_ref.shape[1]
    if p == 1:
        fig, (ax, ax2) = plt.subplots(2, 1, figsize=(9.0, 7.0), height_ratios=(1, 1))
        rows = [(ax, ax2)]
    else:
        fig, grid = plt.subplots(p, 2, figsize=(14.0, 3.6 * p), squeeze=False)
        rows = [(grid[j, 0], grid[j, 1]) for j in range(p)]
    y_unit = _unit(inputs[0].log)[0]
    for j, (ax, ax2) in enumerate(rows):
        which = f"{axis_name(inputs[0].log, 'output', j)}: " if p > 1 else ""
        for i, item in enumerate(inputs):
            sig = item.signals
            if j >= sig.y_ref.shape[1]:
                continue
            truth = sig.has_truth.any()
            e = sig.y_ref[:, j] - (sig.y_true if truth else sig.y_meas)[:, j]
            label = f"{_label(item.log)}{'' if truth else ' (vs measured)'}"
            _line(ax, sig.t_s, e, color=f"C{i}", lw=1.0, label=label)
            window = sig.t_s >= from_s
            if window.any():
                _line(ax2, sig.t_s[window], e[window], color=f"C{i}", lw=1.0, label=label)
        ax.axvline(from_s, color="0.5", ls=":", lw=1.0, label=f"metrics window from {from_s:g} s")
        ylabel = (
            f"{which}reference - output [{y_unit}]" if p == 1 else f"{which.rstrip(': ')} error [{y_unit}]"
        )
        ax.set(xlabel="time [s]", ylabel=ylabel,
               title=_title(inputs, f"{which}tracking error, whole run"))  # fmt: skip
        ax2.set(xlabel="time [s]", ylabel=ylabel,
                title=f"{which}tracking error from {from_s:g} s (the metrics window)")  # fmt: skip
        for a in (ax, ax2):
            a.grid(True, alpha=0.3)
        (ax if p == 1 else ax2).legend(
            *ax.get_legend_handles_labels(), loc="upper left", bbox_to_anchor=(1.01, 1.0),
            fontsize=LEGEND_FONTSIZE, frameon=False,
        )  # fmt: skip
    fig.subplots_adjust(hspace=0.45 if p == 1 else 0.6, wspace=0.25)
    return _save(plt, fig, out)


def _plot_command(plt: Any, inputs: list[PlotInput], out: Path) -> Path:
    """One panel per run and plant input: neither hides the other."""
    m = max(int(item.log.data.samples["u_cmd_a"].shape[1]) for item in inputs)
    panels = [(item, i, j) for i, item in enumerate(inputs) for j in range(m)]
    n = len(panels)
    fig, axes = plt.subplots(n, 1, figsize=(9.0, 2.0 + 2.6 * n), sharex=True, squeeze=False)
    u_unit = _unit(inputs[0].log)[1]
    for (item, i, j), ax in zip(panels, axes[:, 0], strict=True):
        s, t = item.log.data.samples, item.signals.t_s
        if j >= s["u_cmd_a"].shape[1]:
            continue
        cmd = np.asarray(s["u_cmd_a"][:, j], dtype=np.float64)
        applied = np.asarray(s["u_applied_a"][:, j], dtype=np.float64)
        _line(ax, t, cmd, color="0.3", lw=0.8, ls="--", label="commanded (before the limit)")
        _line(ax, t, applied, color=f"C{i}", lw=1.3, label="applied (limited, quantised)")
        limit = item.log.current_limit_A
        if limit is not None:
            ax.axhline(limit, color="r", ls=":", lw=1.0, label=f"current limit +-{limit:g} {u_unit}")
            ax.axhline(-limit, color="r", ls=":", lw=1.0)
            # linear within the limit, logarithmic beyond: a 30 A spike and a 0.2 A ripple both show
            ax.set_yscale("symlog", linthresh=limit, linscale=2.0)
            top = max(float(np.nanmax(np.abs(cmd))) if len(cmd) else limit, limit) * 1.3
            ax.set_ylim(-top, top)
            ax.set_yticks(_symlog_ticks(limit, top))
            ax.yaxis.set_major_formatter(plt.FuncFormatter(lambda v, _pos: f"{v:g}"))
            ax.yaxis.set_minor_locator(plt.NullLocator())
        title = _label(item.log) if m == 1 else f"{_label(item.log)}: {axis_name(item.log, 'input', j)}"
        ax.set(ylabel=f"current [{u_unit}]", title=title)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=LEGEND_FONTSIZE, frameon=False)
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(_title(inputs, "current command and limit (symmetric log scale beyond the limit)"))
    return _save(plt, fig, out)


def _symlog_ticks(limit: float, top: float) -> list[float]:
    """Ticks of the command axis: -limit, -limit/2, 0, limit/2, limit, then decades beyond."""
    ticks = [-limit, -0.5 * limit, 0.0, 0.5 * limit, limit]
    decade = 10.0 ** np.ceil(np.log10(limit * 1.5))
    while decade <= top:
        ticks += [decade, -decade]
        decade *= 10.0
    return sorted(ticks)


def _plot_timing(plt: Any, inputs: list[PlotInput], out: Path) -> Path | None:
    """Real-time logs only: a lockstep run's times are host wall-clock times of a simulation."""
    realtime = [(i, item) for i, item in enumerate(inputs) if item.log.mode != "lockstep"]
    if not realtime:
        return None
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11.0, 4.5))
    for i, item in realtime:
        s, fb = item.log.data.samples, item.signals.has_feedback
        rx = s["rx_time_ns"].astype(np.int64)
        tx = s["tx_time_ns"].astype(np.int64)
        latency_us = (tx - rx)[fb & (tx > 0)] * 1e-3
        pair = fb[1:] & fb[:-1] & (np.diff(s["seq"].astype(np.int64)) == 1)
        jitter_us = np.abs(np.diff(rx) - item.log.period_ns)[pair] * 1e-3
        for ax, values in ((ax1, latency_us), (ax2, jitter_us)):
            if len(values):
                ax.hist(values, bins=HIST_BINS, color=f"C{i}", alpha=0.5, log=True, label=_label(item.log))
    ax1.set(xlabel="feedback receive -> command send [us]", ylabel="samples", title="latency")
    ax2.set(xlabel="|receive interval - period| [us]", ylabel="samples", title="period jitter")
    for ax in (ax1, ax2):
        ax.grid(True, alpha=0.3)
        ax.xaxis.set_major_locator(plt.MaxNLocator(5))
        if not ax.patches:
            ax.text(0.5, 0.5, "no samples to show", transform=ax.transAxes, ha="center", color="0.4")
    _legend_below(fig, ax1, ncol=1)
    fig.suptitle(_title([item for _, item in realtime], "real-time timing"))
    return _save(plt, fig, out)


def write_plots(inputs: list[PlotInput], out_dir: Path, *, from_s: float) -> list[Path]:
    """Write the PNGs of the module docstring into ``out_dir``; returns their paths."""
    inputs = [item for item in inputs if len(item.log.data.samples)]
    if not inputs:
        return []
    plt = _pyplot()
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [
        _plot_output(plt, inputs, _model_outputs(inputs), out_dir / "output.png"),
        _plot_disturbance(plt, inputs, from_s, out_dir / "disturbance.png"),
    ]
    sens = _plot_sensitivity(plt, inputs, out_dir / "sensitivity.png")
    if sens is not None:
        paths.append(sens)
    paths.append(_plot_tracking(plt, inputs, from_s, out_dir / "tracking_error.png"))
    paths.append(_plot_command(plt, inputs, out_dir / "command.png"))
    timing = _plot_timing(plt, inputs, out_dir / "timing.png")
    if timing is not None:
        paths.append(timing)
    return paths
