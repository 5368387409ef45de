"""A SYNC lost on the way to the simulated CiA 402 drive in lockstep: the drive's time runs on
without it (the runner's advance_period, counted by the SYNC-loss watchdog), and the samples
after the gap are taken at their own instants again (the ODrive counterpart:
tests/odrive/test_lost_trigger.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
from lost_trigger import assert_samples_at_their_instants

SYNC_ID = 0x80


@pytest.mark.parametrize("lost", [1, 3])
def test_samples_after_lost_syncs_are_taken_at_their_own_instants(tmp_path: Path, lost: int) -> None:
    assert_samples_at_their_instants("paper-step-cia402", SYNC_ID, lost, tmp_path / "lost.mcap")
