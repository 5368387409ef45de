"""The lockstep per-period fast paths write the same log as the general paths they shortcut.

Fast paths: the simulated native drive's whole commanded period in one call
(``LockstepClock._exchange``) and the writer's ground-truth hook (``LogWriter.truth_hook``).
Each run is made twice, once as shipped and once with both forced onto the general path
(``DriveCore.lockstep_period`` / ``_on_command`` + ``_send_sample``; ``LogWriter.truth``), on
configs that exercise what the fast paths must hand over: noise, frame loss, a disturbance,
saturation, heartbeat periods, an input delay, a 3-state plant, injected faults. Every channel
must match record for record (``compute_ns`` and wall-clock event fields aside).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dob_hil.config import Config, FaultsConfig, load_config
from dob_hil.log import read_log
from dob_hil.log.writer import LogWriter
from dob_hil.loop.session import RunOptions, run_session
from dob_hil.scenarios import scenario_path
from firmware_sim.lockstep import LockstepClock

DURATION_S = 0.4  # 1333 periods: heartbeats fall due on the way (every 100 ms)


def _variant(name: str) -> Config:
    if name == "noise+loss":
        cfg = load_config(scenario_path("paper-step"))
        sim = dataclasses.replace(cfg.sim, noise_counts_std=2.0, loss_probability=0.03, seed=11)
        return dataclasses.replace(cfg, sim=sim)
    if name == "sine":  # a sine reference and the paper's disturbance
        return load_config(scenario_path("paper-sine"))
    if name == "no-disturbance":
        cfg = load_config(scenario_path("paper-step"))
        return dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, disturbances=()))
    if name == "faults":  # an injected encoder jump: the general path throughout
        cfg = load_config(scenario_path("paper-step"))
        faults = FaultsConfig(encoder_jump_at_s=0.1, encoder_jump_counts=3)
        sim = dataclasses.replace(cfg.sim, faults=faults, loss_probability=0.01, seed=3)
        return dataclasses.replace(cfg, sim=sim)
    if name == "input-delay":  # a delayed current: the fast path declines every period
        cfg = load_config(scenario_path("paper-step-cia402"))  # the design with the delay state
        assert cfg.plant.input_delay_samples == 1
        return dataclasses.replace(cfg, drive=dataclasses.replace(cfg.drive, profile="native"))
    raise AssertionError(name)


VARIANTS = ["noise+loss", "sine", "no-disturbance", "faults", "input-delay"]


def _general_truth_hook(self: LogWriter) -> Callable[[tuple[Any, ...]], None]:
    """The sink before LogWriter.truth_hook: every record through LogWriter.truth."""
    write = self.truth

    def sink(t: tuple[Any, ...]) -> None:
        period_index, time_ns, state, disturbance_A, applied_A, drive_state = t
        write(time_ns, state, (disturbance_A,), (applied_A,), period_index, drive_state)

    return sink


def _run(cfg: Config, path: Path) -> None:
    summary = run_session(cfg, RunOptions(duration_s=DURATION_S, log_path=path))
    assert summary.log_dropped_records == 0


def _assert_same_log(a: Path, b: Path) -> None:
    da, db = read_log(a), read_log(b)
    sa, sb = da.samples, db.samples
    assert len(sa) == len(sb) > 0
    for field in sa.dtype.names or ():
        if field != "compute_ns":
            np.testing.assert_array_equal(sa[field], sb[field], err_msg=field)
    for name in ("frames", "fd_frames", "truth"):
        assert np.array_equal(getattr(da, name), getattr(db, name)), name
    assert len(da.truth) >= len(sa)

    def strip(events: list[dict[str, Any]]) -> list[list[tuple[str, Any]]]:
        return [sorted((k, v) for k, v in e.items() if k != "wall_time_ns") for e in events]

    assert strip(da.events) == strip(db.events)


@pytest.mark.parametrize("variant", VARIANTS)
def test_fast_paths_log_the_same_records_as_the_general_paths(
    variant: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = _variant(variant)
    taken = 0
    exchange = LockstepClock._exchange

    def counting(self: LockstepClock, current_counts: int, seq7: int) -> bool:
        nonlocal taken
        done = exchange(self, current_counts, seq7)
        taken += done
        return done

    monkeypatch.setattr(LockstepClock, "_exchange", counting)
    _run(cfg, tmp_path / "fast.mcap")
    periods = round(DURATION_S * 1e9 / cfg.plant.period_ns)
    if variant in ("faults", "input-delay"):
        assert taken == 0
    else:  # all but the heartbeat periods (and the lost feedback's, which the host cannot answer)
        assert taken > periods * 0.9
    monkeypatch.setattr(LockstepClock, "_exchange", lambda self, current_counts, seq7: False)
    monkeypatch.setattr(LogWriter, "truth_hook", _general_truth_hook)
    _run(cfg, tmp_path / "general.mcap")
    _assert_same_log(tmp_path / "fast.mcap", tmp_path / "general.mcap")


def test_fused_flag_selects_the_general_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``LockstepClock.fused = False`` (the switch the clock offers) gives the same log too."""
    cfg = _variant("noise+loss")
    _run(cfg, tmp_path / "fast.mcap")
    init = LockstepClock.__init__

    def general_init(self: LockstepClock, *args: Any, **kwargs: Any) -> None:
        init(self, *args, **kwargs)
        self.fused = False

    monkeypatch.setattr(LockstepClock, "__init__", general_init)
    _run(cfg, tmp_path / "general.mcap")
    _assert_same_log(tmp_path / "fast.mcap", tmp_path / "general.mcap")
