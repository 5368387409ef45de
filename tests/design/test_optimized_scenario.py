"""paper-step-optimized against paper-step in lockstep: 3x less tracking error from the paper's 4 Hz
and 12 Hz disturbances, no more current noise from encoder noise (issue 15)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dob_hil.config import parse_config_text
from dob_hil.log import read_log
from dob_hil.loop.session import RunOptions, run_session
from dob_hil.scenarios import scenario_path

TWELVE_HZ = """
[[sim.disturbance]]
kind = "sine"
amplitude_A = 0.1
frequency_hz = 12.0
"""


def _run(
    name: str, tmp_path: Path, *, twelve_hz: bool, noise_counts: float, seed: int = 0, duration_s: float = 1.0
) -> tuple[Any, Any]:
    text = scenario_path(name).read_text()
    for old, new in (
        ("noise_counts_std = 0.0\n", f"noise_counts_std = {noise_counts}\n"),
        ("seed = 0\n", f"seed = {seed}\n"),
        ("duration_s = 1.0\n", f"duration_s = {duration_s}\n"),
    ):
        assert old in text
        text = text.replace(old, new)
    if twelve_hz:
        text = text.replace("\n[reference]", TWELVE_HZ + "\n[reference]")
    cfg = parse_config_text(text, source=scenario_path(name))
    log = tmp_path / f"{name}-{twelve_hz}-{noise_counts}-{seed}.mcap"
    summary = run_session(cfg, RunOptions(log_path=log))
    assert summary.exit_reason == "completed"
    data = read_log(log)
    return data.samples, data.truth


def _steady_error_rms(name: str, tmp_path: Path, twelve_hz: bool) -> float:
    s, t = _run(name, tmp_path, twelve_hz=twelve_hz, noise_counts=0.0)
    window = s["time_ns"] >= 0.3e9  # after the step's transient
    err = s["x_ref"][window, 0] - t["state"][: len(s), 0][window]
    return float(np.sqrt(np.mean(err**2)))


@pytest.mark.parametrize("twelve_hz", [False, True], ids=["4Hz", "4Hz+12Hz"])
def test_optimized_gains_reject_the_papers_disturbance_3x_better_in_lockstep(
    tmp_path: Path, twelve_hz: bool
) -> None:
    paper = _steady_error_rms("paper-step", tmp_path, twelve_hz)
    optimized = _steady_error_rms("paper-step-optimized", tmp_path, twelve_hz)
    assert paper / optimized >= 3.0


def test_optimized_gains_add_no_current_noise_in_lockstep(tmp_path: Path) -> None:
    """Encoder noise of one count RMS: the command's deviation from the noise-free run, over 3 s and
    two noise seeds (the sample RMS of one 1 s path scatters by a few %)."""
    rms = {}
    for name in ("paper-step", "paper-step-optimized"):
        clean, _ = _run(name, tmp_path, twelve_hz=False, noise_counts=0.0, duration_s=3.0)
        window = clean["time_ns"] >= 0.3e9
        diffs = []
        for seed in (1, 2):
            noisy, _ = _run(name, tmp_path, twelve_hz=False, noise_counts=1.0, seed=seed, duration_s=3.0)
            diffs.append(noisy["u_cmd_a"][window, 0] - clean["u_cmd_a"][window, 0])
        rms[name] = float(np.sqrt(np.mean(np.concatenate(diffs) ** 2)))
    # Equal RMS noise-to-current by design (0.0372 A per count RMS); the simulated encoder rounds
    # noise and position to whole counts, which adds about 10 % to both.
    assert rms["paper-step"] == pytest.approx(0.0372 * 1.1, rel=0.08)
    assert rms["paper-step-optimized"] <= 1.03 * rms["paper-step"]
