"""A trigger (RTR) lost on the way to the simulated ODrive in lockstep: the drive's time runs on
without it, and the samples after the gap are taken at their own instants again (before the fix,
every later sample was the previous instant's)."""

from __future__ import annotations

from pathlib import Path

import pytest
from lost_trigger import assert_samples_at_their_instants

from .test_fault_matrix import EST_ID


@pytest.mark.parametrize("lost", [1, 3])
def test_samples_after_lost_triggers_are_taken_at_their_own_instants(tmp_path: Path, lost: int) -> None:
    assert_samples_at_their_instants("paper-step-odrive", EST_ID, lost, tmp_path / "lost.mcap")
