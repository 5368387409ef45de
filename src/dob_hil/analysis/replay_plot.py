"""The plot of ``replay --design``: the current sent and what another design would have sent."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from dob_hil.analysis.downsample import envelope
from dob_hil.analysis.loaded import LoadedLog
from dob_hil.analysis.plots import DPI
from dob_hil.analysis.replay import RedesignSeries

FloatArray = npt.NDArray[np.float64]


def plot_redesign(log: LoadedLog, series: RedesignSeries, design_name: str, path: Path) -> Path:
    """Per plant input: applied current sent vs the other design's (upper panel) and their
    difference (lower panel), from the decimated series of :func:`replay.redesign_blocks`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dob_hil.analysis.plots import axis_name, literal

    t = series.t_s
    m = int(series.sent_A.shape[1])
    unit = literal(log.design.input_unit) if log.design is not None else "A"
    fig, axes = plt.subplots(
        2 * m, 1, figsize=(9.0, 7.0 * m), sharex=True, height_ratios=(2, 1) * m, squeeze=False
    )
    for j in range(m):
        ax, ax2 = axes[2 * j, 0], axes[2 * j + 1, 0]
        which = f"{axis_name(log, 'input', j)}: " if m > 1 else ""
        sent: FloatArray = np.asarray(series.sent_A[:, j], dtype=np.float64)
        other: FloatArray = np.asarray(series.other_A[:, j], dtype=np.float64)
        diff: FloatArray = np.asarray(other - sent, dtype=np.float64)
        ax.plot(*envelope(t, sent), color="C0", lw=1.2, label=f"sent ({literal(log.label)})")
        ax.plot(*envelope(t, other), color="C1", lw=1.0,
                label=f"{literal(design_name)} (open loop, same measurements)")  # fmt: skip
        title = f"{literal(log.path.name)}: {which}what {literal(design_name)} would have commanded"
        ax.set(ylabel=f"{which}applied current [{unit}]", title=title)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
        ax2.plot(*envelope(t, diff), color="C2", lw=1.0)
        ax2.set(xlabel="time [s]", ylabel=f"{which}other - sent [{unit}]")
        ax2.grid(True, alpha=0.3)
        ax2.tick_params(labelbottom=True)
    if m > 1:
        fig.subplots_adjust(hspace=0.45)
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return path
