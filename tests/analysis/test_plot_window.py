"""Plots of a long log come from a window read through the chunk index, in bounded memory."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dob_hil.analysis import plot_window
from dob_hil.analysis.plots import PlotInput
from dob_hil.commands import analyze as analyze_command
from dob_hil.log import read_log

PERIOD_S = 300e-6  # the paper scenarios' period


@pytest.fixture(scope="module")
def long_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3 s paper-sine lockstep log (10,000 samples, about 15 chunks)."""
    from dob_hil.config import load_config
    from dob_hil.loop.session import RunOptions, run_session
    from dob_hil.scenarios import scenario_path

    path = tmp_path_factory.mktemp("window") / "sine.mcap"
    run_session(load_config(scenario_path("paper-sine")), RunOptions(duration_s=3.0, log_path=path))
    return path


def _capture_plots(monkeypatch: pytest.MonkeyPatch) -> list[list[PlotInput]]:
    seen: list[list[PlotInput]] = []
    from dob_hil.analysis import plots

    monkeypatch.setattr(plots, "write_plots", lambda inputs, out_dir, *, from_s: seen.append(inputs) or [])
    return seen


def test_a_window_read_decompresses_only_the_chunks_it_overlaps(long_log: Path) -> None:
    whole = read_log(long_log)
    t_ns = whole.samples["time_ns"].astype(np.int64)
    first_ns, last_ns = int(t_ns[0] + 1.0e9), int(t_ns[0] + 1.2e9)
    part = read_log(long_log, log_time_window_ns=(first_ns, last_ns))
    got = part.samples["time_ns"].astype(np.int64)
    inside = whole.samples[(t_ns >= first_ns) & (t_ns <= last_ns)]
    assert len(inside) == 667
    # every sample of the window is there, bit for bit, and far less than the whole log
    np.testing.assert_array_equal(part.samples[(got >= first_ns) & (got <= last_ns)], inside)
    assert len(part.samples) < len(whole.samples) / 4
    assert got[0] <= first_ns + 2 * PERIOD_S * 1e9 and got[-1] >= last_ns - 2 * PERIOD_S * 1e9
    assert len(part.truth) < len(whole.truth) / 4 and part.metadata == whole.metadata


def test_a_long_log_is_plotted_from_its_first_samples_and_analysed_whole(
    long_log: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    monkeypatch.setattr(analyze_command, "STREAM_ABOVE_SAMPLES", 2000)
    [expected] = analyze_command.analyze_logs(
        [long_log], from_s=0.1, plots_dir=None, as_json=True, plots=False
    )
    capsys.readouterr()
    read: list[Any] = []
    real_read = plot_window.read_log
    monkeypatch.setattr(plot_window, "read_log", lambda *a, **k: read.append(k) or real_read(*a, **k))
    seen = _capture_plots(monkeypatch)
    got = analyze_command.analyze_logs([long_log], from_s=0.1, plots_dir=tmp_path / "p", as_json=False)
    out = capsys.readouterr().out
    assert "plots of long logs show a window (--plot-window START:END chooses it): sine.mcap: 0-0.6 s" in out
    # the metrics cover the whole log, streamed as without plots, not the window
    assert {k: v for k, v in got[0].items() if k != "plots"} == {
        k: v for k, v in expected.items() if k != "plots"
    }
    assert got[0]["samples"] == 9666 and got[0]["plots"] == []  # 0.1 s to 3 s
    assert [k["log_time_window_ns"] is not None for k in read] == [True]
    [[item]] = seen
    assert len(item.log.data.samples) == 2001  # 0 .. 0.6 s, both ends included
    assert item.signals.t_s[0] == 0.0 and item.signals.t_s[-1] == pytest.approx(0.6)


def test_a_chosen_window_is_plotted_with_times_from_the_first_sample(
    long_log: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setattr(analyze_command, "STREAM_ABOVE_SAMPLES", 2000)
    seen = _capture_plots(monkeypatch)
    got = analyze_command.analyze_logs(
        [long_log], from_s=0.1, plots_dir=tmp_path / "p", as_json=True, plot_window_s=(2.0, 2.5)
    )
    assert got[0]["plot_window_s"] == [2.0, 2.5]
    [[item]] = seen
    assert item.signals.t_s[0] == pytest.approx(2.0, abs=PERIOD_S)
    assert item.signals.t_s[-1] == pytest.approx(2.5, abs=PERIOD_S)
    assert np.all(item.signals.truth.index >= 0)  # truth matched in the window
    # a short log (read whole) with a window: the same stretch
    monkeypatch.setattr(analyze_command, "STREAM_ABOVE_SAMPLES", 100_000)
    analyze_command.analyze_logs(
        [long_log], from_s=0.1, plots_dir=tmp_path / "q", as_json=True, plot_window_s=(2.0, 2.5)
    )
    short = seen[-1][0]
    np.testing.assert_array_equal(short.log.data.samples, item.log.data.samples)
    np.testing.assert_array_equal(short.signals.y_true, item.signals.y_true)


def test_the_window_of_a_long_log_is_bounded(long_log: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(plot_window, "MAX_WINDOW_SAMPLES", 1000)
    with pytest.raises(plot_window.ConfigError, match=r"--plot-window.*more than 1,000 samples.*0\.3 s"):
        plot_window.window_of_long_log(long_log, 0, 3 * 10**9, 300_000, (0.0, 1.0))
    log, signals = plot_window.window_of_long_log(long_log, 0, 3 * 10**9, 300_000, (0.0, 0.3))
    assert 900 <= len(log.data.samples) <= 1001 and len(signals.t_s) == len(log.data.samples)


@pytest.mark.parametrize(
    ("arg", "problem"),
    [
        ("abc", "expected START:END"),
        ("1:2:3", "expected START:END"),
        ("5:1", "0 <= START < END"),
        ("-1:2", "0 <= START < END"),
        ("nan:3", "0 <= START < END"),
        ("2:inf", "0 <= START < END"),
        ("100:200", "holds no samples"),
        ("1:2 --no-plots", "no plots"),
    ],
)
def test_a_bad_plot_window_is_one_line(long_log: Path, tmp_path: Path, arg: str, problem: str) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "dob_hil.cli", "analyze", str(long_log), "--plots", str(tmp_path / "p"),
         f"--plot-window={arg.split(maxsplit=1)[0]}", *arg.split()[1:]],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "--plot-window" in lines[0] and problem in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr
