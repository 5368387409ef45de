"""The host's link against what a correct drive may do (PROTOCOL.md leaves it free): a drive that
restarts its feedback sequence on enable, one that faults on a COMMAND while DISABLED, one that pads
every frame to 8 bytes. Each runs enable, a closed loop, the stop sequence and a second enable with
the simulated drive (lockstep) and must end DISABLED, with nothing rejected or discarded."""

from __future__ import annotations

import can
import pytest

from dob_hil.config import DriveConfig
from dob_hil.link.native import NativeDriveLink
from dob_hil.link.protocol import DriveState, FrameKind
from firmware_sim import SimulatedDrive
from firmware_sim.behaviour import VARIANTS, DriveBehaviour

from .conftest import Recorder
from .test_variants_support import lockstep_config

PERMITTED = ["reference", "restart-sequence", "fault-on-command-while-disabled", "padded"]


def enable(link: NativeDriveLink, drive: SimulatedDrive) -> None:
    link.request_enable()
    for _ in range(3):
        drive.service()
        if link.poll_enabled():
            return
    raise AssertionError(f"not enabled: {link.drive_state}")


def run_periods(link: NativeDriveLink, drive: SimulatedDrive, n: int) -> list[int]:
    seqs = []
    for _ in range(n):
        fb = link.receive_feedback(0)
        assert fb is not None and fb.enabled
        seqs.append(fb.seq)
        codes, _, _ = link.quantize((0.01,))
        link.send_command(codes, fb.seq)
        drive.service()
    return seqs


@pytest.mark.parametrize("variant", PERMITTED)
def test_the_host_runs_every_permitted_drive_variant(
    variant: str, bus_pair: tuple[can.BusABC, can.BusABC]
) -> None:
    host_bus, drive_bus = bus_pair
    behaviour: DriveBehaviour = VARIANTS[variant]
    drive = SimulatedDrive(drive_bus, lockstep_config(), behaviour=behaviour)
    rec = Recorder()
    link = NativeDriveLink(host_bus, DriveConfig(), frame_hook=rec.frame, event_hook=rec.event)
    for cycle in range(2):  # the second enable shows a restarted sequence
        enable(link, drive)
        seqs = run_periods(link, drive, 20)
        if behaviour.restart_sequence_on_enable:
            assert seqs[0] == 0, seqs  # the drive restarted its counter on (re-)enable
        link.safe_stop()
        while drive.service():
            pass
        assert drive.state is DriveState.DISABLED, f"cycle {cycle}: {drive.state.name}"
    link.close()  # no second stop sequence
    drive.service()
    assert drive.state is DriveState.DISABLED
    assert link.stats.malformed_frames == 0 and link.stats.stale_feedback == 0, rec.kinds()
    assert link.stats.drive_faults == 0
    # one stop sequence per run: a zero COMMAND with the enable bit clear, then CONTROL disable
    sent = [(m.arbitration_id, bytes(m.data)) for m, is_rx in rec.frames if not is_rx]
    stops = [i for i, (aid, data) in enumerate(sent) if aid == FrameKind.COMMAND + 1 and not data[2] & 0x80]
    assert len(stops) == 2
    for i in stops:
        assert sent[i][1][:2] == b"\x00\x00"
        assert sent[i + 1] == (FrameKind.CONTROL + 1, b"\x00\x02")
    assert sent[-1] == (FrameKind.CONTROL + 1, b"\x00\x02")


def test_a_drive_faulting_on_commands_while_disabled_is_not_faulted_by_a_stop_before_enable(
    bus_pair: tuple[can.BusABC, can.BusABC],
) -> None:
    """A host that stops a drive it never enabled (a run refused early) sends CONTROL disable only."""
    host_bus, drive_bus = bus_pair
    drive = SimulatedDrive(
        drive_bus, lockstep_config(), behaviour=VARIANTS["fault-on-command-while-disabled"]
    )
    link = NativeDriveLink(host_bus, DriveConfig())
    link.safe_stop()
    link.close()
    drive.service()
    assert drive.state is DriveState.DISABLED
    # the variant does fault on a COMMAND while DISABLED: what a second stop COMMAND would have done
    drive_bus_host = NativeDriveLink(host_bus, DriveConfig())
    drive_bus_host.send_command((0,), 0)
    drive.service()
    assert drive.state is DriveState.FAULT
