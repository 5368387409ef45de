"""Every design plot (what ``dob-hil design`` and the demo write) passes the analyze plots' check."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from test_plots import check_figure

from dob_hil.config import load_config
from dob_hil.design import design_with_diagnostics
from dob_hil.design import plots as design_plots
from dob_hil.design.analysis import analyze
from dob_hil.scenarios import resolve_config_path


@pytest.mark.parametrize("scenario", ["paper-step", "paper-step-optimized"])
def test_every_design_plot_is_labelled_and_uncovered(
    scenario: str, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import matplotlib.pyplot as plt

    kept: dict[str, Any] = {}
    save = design_plots._save

    def keep(fig: Any, out: Path, plt_: Any) -> Path:
        kept[out.name] = fig
        fig.canvas.draw()
        return out

    monkeypatch.setattr(design_plots, "_save", keep)
    config = load_config(resolve_config_path(scenario))
    written = design_plots.write_plots(analyze(design_with_diagnostics(config), config), tmp_path)
    assert {p.name for p in written} == set(kept)
    try:
        for name, fig in kept.items():
            check_figure(name, fig)
    finally:
        for fig in kept.values():
            plt.close(fig)
    assert save is not keep
