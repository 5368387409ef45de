"""Fixtures: short real runs of both paper scenarios with and without the DOB (lockstep)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from analysis_support import run_log, scenario_text

from dob_hil.analysis import plots

RUN_S = 0.3  # 1000 samples: long enough for the disturbance (4 Hz) to act over a period


@pytest.fixture(scope="session")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[tuple[str, bool], Path]:
    """{(scenario, dob_enabled): log path} for paper-step and paper-sine, DOB on and off."""
    out = tmp_path_factory.mktemp("runs")
    logs = {}
    for scenario in ("paper-step", "paper-sine"):
        for dob in (True, False):
            path = out / f"{scenario}-{'dob' if dob else 'nodob'}.mcap"
            logs[(scenario, dob)] = run_log(path, scenario_text(scenario), dob=dob, duration_s=RUN_S)
    return logs


@pytest.fixture()
def figures(monkeypatch: pytest.MonkeyPatch) -> Iterator[dict[str, Any]]:
    """The figures plots.py saves, by file name, kept open for inspection."""
    kept: dict[str, Any] = {}

    def keep(plt: Any, fig: Any, out: Path) -> Path:
        fig.savefig(out, dpi=plots.DPI, bbox_inches="tight")
        kept[out.name] = fig
        return out

    monkeypatch.setattr(plots, "_save", keep)
    yield kept
    import matplotlib.pyplot as plt

    for fig in kept.values():
        plt.close(fig)
