"""replay --verify against the loop's own ControlCycle, driven sample by sample through every
branch (feedback, missing feedback under each policy, a slot lost unanswered), so the replay is
checked against the real loop code independently of the simulated drive."""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path

import numpy as np
import pytest
from analysis_support import scenario_text

from dob_hil.analysis import load_log
from dob_hil.analysis.replay import verify
from dob_hil.config import Config, parse_config_text
from dob_hil.control.reference import make_reference
from dob_hil.control.step import Gains, compile_step
from dob_hil.design import build_design
from dob_hil.link.base import Feedback
from dob_hil.link.native import DacQuantizer
from dob_hil.log import LogLayout, LogWriter, run_metadata
from dob_hil.log.schemas import FLAG_FEEDBACK_MISSING
from dob_hil.loop.cycle import ControlCycle

N = 400
MISSING = {0, 1, 50, 51, 52, 53, 120, 250, 251}  # at the start (no feedback yet) and in bursts
LOST = {80, 81, 200, 252}


class StubLink:
    """The DriveLink calls the cycle makes, with the native quantizer; records what was sent."""

    def __init__(self, config: Config) -> None:
        self._quantizer = DacQuantizer(config.drive)
        self.applied_A = 0.0
        self._clock = itertools.count(1_000_000, 1000)

    def quantize(self, current_A: tuple[float, ...]) -> tuple[tuple[int, ...], tuple[float, ...], bool]:
        codes, applied, saturated = self._quantizer.quantize(current_A)
        self._pending = applied[0]
        return codes, applied, saturated

    def send_command(self, codes: tuple[int, ...], answers_seq: int) -> int:
        self.applied_A = self._pending
        return next(self._clock)


def _write_run(path: Path, config: Config, dob: bool) -> None:
    design = build_design(config, dob_enabled=dob)
    step = compile_step(Gains(design.Phi, design.Gam, design.C, design.Lc, design.Kc, design.Kdist), dob)
    layout = LogLayout(step.n_states, step.n_inputs, step.n_outputs, config.plant.n_states)
    meta = run_metadata(
        mode="lockstep",
        bus="stub",
        period_ns=config.plant.period_ns,
        layout=layout,
        dob_enabled="true" if dob else "false",
    )
    attachments = {"design.json": design.to_json().encode(), "config.toml": config.text.encode()}
    link = StubLink(config)
    with LogWriter(path, layout, metadata={"run": meta}, attachments=attachments) as log:
        cycle = ControlCycle(
            step,
            make_reference(config.reference, step.n_states, config.plant.period_s),
            link,
            log,  # type: ignore[arg-type]
            dob_enabled=dob,
            missing_policy=config.run.missing_feedback_policy,
            max_missing_periods=config.run.max_missing_periods,
            C_rows=tuple(tuple(float(c) for c in row) for row in design.C),
        )
        x = np.zeros(2)
        for k in range(N):
            t_ns = k * config.plant.period_ns
            counts = round(float(x[0]) * config.drive.encoder_counts_per_unit)
            if k in LOST:
                cycle.on_lost(k, t_ns, k % 256)
            elif k in MISSING:
                cycle.on_missing(k, t_ns, k % 256, 0, False)
            else:
                fb = Feedback(
                    t_ns + 100,
                    k % 256,
                    (counts,),
                    (counts,),
                    (counts / config.drive.encoder_counts_per_unit,),
                    True,
                    False,
                    False,
                )
                cycle.on_feedback(k, t_ns, fb, 0, False)
            w_A = 0.2 * np.sin(8 * np.pi * t_ns * 1e-9)
            x = design.Phi @ x + design.Gam[:, 0] * (link.applied_A + w_A)


@pytest.mark.parametrize(("policy", "dob"), [("hold", True), ("extrapolate", False), ("zero", True)])
def test_verify_matches_the_loop_cycle_in_every_branch(tmp_path: Path, policy: str, dob: bool) -> None:
    text = scenario_text(
        "paper-step",
        **{
            "dob_enabled = true\n": f"dob_enabled = true\n"
            f"missing_feedback_policy = '{policy}'\nmax_missing_periods = 2\n"
        },
    )
    path = tmp_path / f"{policy}.mcap"
    _write_run(path, parse_config_text(text), dob)
    log = load_log(path)
    flags = log.data.samples["flags"]
    assert np.count_nonzero(flags & FLAG_FEEDBACK_MISSING) == len(MISSING) + len(LOST)
    result = verify(log)
    assert result.identical, result.first_mismatches
    assert result.samples == N


def test_verify_detects_a_policy_the_run_did_not_use(tmp_path: Path) -> None:
    """The log claims 'hold' but the loop ran 'extrapolate': the substitutes differ."""
    ran = parse_config_text(
        scenario_text(
            "paper-step",
            **{"dob_enabled = true\n": "dob_enabled = true\nmissing_feedback_policy = 'extrapolate'\n"},
        )
    )
    claimed = parse_config_text(scenario_text("paper-step"))
    path = tmp_path / "liar.mcap"
    _write_run(path, dataclasses.replace(ran, text=claimed.text), True)
    result = verify(load_log(path))
    assert not result.identical
    assert result.first_mismatch_seq == 50  # the first missing sample after feedback began
    assert result.mismatches_by_field["position"] > 0
