"""A drive left in FAULT by a killed host (issue 11): the next run names the fault and the remedy,
and ``dob-hil run --clear-fault`` recovers it. The drive runs in its own process over udp_multicast
on a private port (CAN_CONFIG), as the README's cross-process example."""

from __future__ import annotations

import json
import random
from pathlib import Path

import can
import pytest

from dob_hil.cli import main
from dob_hil.config import load_config
from dob_hil.link.bus import open_bus
from dob_hil.link.native import NativeDriveLink
from dob_hil.link.protocol import DriveState
from dob_hil.scenarios import scenario_variant
from firmware_sim.process import standalone_drive

pytestmark = pytest.mark.realtime
WATCHDOG = 1000  # periods of 300 us (and the host's timeout as wide): a loaded machine stalls


def leave_in_watchdog_fault(config_path: Path, channel: str) -> None:
    """A host that enables, answers one feedback and dies (no stop sequence)."""
    config = load_config(config_path)
    bus = open_bus("udp_multicast", channel)
    link = NativeDriveLink(bus, config.drive)
    link.enable(20_000_000_000)
    fb = link.receive_feedback(5_000_000_000)
    assert fb is not None
    link.send_command((0,), fb.seq)
    while link.drive_state is not DriveState.FAULT:  # the drive's watchdog trips
        link.receive_feedback(1_000_000_000)
    bus.shutdown()  # killed: never safe_stop()


def test_a_drive_left_in_fault_is_named_and_cleared(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    port = random.randint(46000, 46999)
    monkeypatch.setenv("CAN_CONFIG", json.dumps({"port": port}))
    channel = f"239.74.163.{random.randint(10, 250)}"
    cfg = scenario_variant("paper-step", tmp_path, node_id=random.randint(2, 15), patience_periods=WATCHDOG)
    try:
        can.Bus(interface="udp_multicast", channel=channel, port=port).shutdown()
    except (OSError, can.CanError) as exc:
        pytest.skip(f"udp_multicast unavailable: {exc}")
    run = ["run", str(cfg), "-i", "udp_multicast", "-c", channel, "--duration", "0.2", "--no-progress",
           "--log", str(tmp_path / "run.mcap"), "--feedback-timeout-periods", "3000"]  # fmt: skip
    with standalone_drive(cfg, "udp_multicast", channel) as drive:
        leave_in_watchdog_fault(cfg, channel)
        assert main(run) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1
        assert "WATCHDOG (info 255: periods without a valid command)" in err  # info is capped at 255
        assert "--clear-fault" in err
        status = main([*run, "--clear-fault"])
        if status:
            from dob_hil.log import read_log

            raise AssertionError([e["message"] for e in read_log(tmp_path / "run.mcap").events])
        assert status == 0, capsys.readouterr()
        assert drive.alive()
    assert drive.exit_status == 0
    assert "final state DISABLED" in drive.stderr_text
