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
    """Applied current sent vs the other design's (top) and their difference (bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = log.data.samples
    t_ns = s["time_ns"].astype(np.int64)
    t: FloatArray = np.asarray((t_ns - (t_ns[0] if len(t_ns) else 0)) * 1e-9, dtype=np.float64)
    sent: FloatArray = np.asarray(s["u_applied_a"][:, 0], dtype=np.float64)
    other: FloatArray = np.asarray(rerun.u_applied[:, 0], dtype=np.float64)
    diff: FloatArray = np.asarray(other - sent, dtype=np.float64)
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(9.0, 7.0), sharex=True, height_ratios=(2, 1))
    ax.plot(*envelope(t, sent), color="C0", lw=1.2, label=f"sent ({log.label})")
    ax.plot(*envelope(t, other), color="C1", lw=1.0, label=f"{design_name} (open loop, same measurements)")
    ax.set(ylabel="applied current [A]", title=f"{log.path.name}: what {design_name} would have commanded")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    ax2.plot(*envelope(t, diff), color="C2", lw=1.0)
    ax2.set(xlabel="time [s]", ylabel="other - sent [A]")
    ax2.grid(True, alpha=0.3)
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return path
