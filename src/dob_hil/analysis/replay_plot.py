"""The plot of ``replay --design``: the current sent and what another design would have sent."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from dob_hil.analysis.downsample import envelope
from dob_hil.analysis.loaded import LoadedLog
from dob_hil.analysis.plots import DPI
from dob_hil.analysis.rerun import Rerun

FloatArray = npt.NDArray[np.float64]


def plot_redesign(log: LoadedLog, rerun: Rerun, design_name: str, path: Path) -> Path:
    """Per plant input: applied current sent vs the other design's (upper panel) and their
    difference (lower panel)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dob_hil.analysis.plots import axis_name, literal

    s = log.data.samples
    t_ns = s["time_ns"].astype(np.int64)
    t: FloatArray = np.asarray((t_ns - (t_ns[0] if len(t_ns) else 0)) * 1e-9, dtype=np.float64)
    m = int(s["u_applied_a"].shape[1])
    unit = literal(log.design.input_unit) if log.design is not None else "A"
    fig, axes = plt.subplots(
        2 * m, 1, figsize=(9.0, 7.0 * m), sharex=True, height_ratios=(2, 1) * m, squeeze=False
    )
    for j in range(m):
        ax, ax2 = axes[2 * j, 0], axes[2 * j + 1, 0]
        which = f"{axis_name(log, 'input', j)}: " if m > 1 else ""
        sent: FloatArray = np.asarray(s["u_applied_a"][:, j], dtype=np.float64)
        other: FloatArray = np.asarray(rerun.u_applied[:, j], dtype=np.float64)
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
