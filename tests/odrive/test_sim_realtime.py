"""The simulated ODrive on its real-time clock, in this process: the link enables it through the
heartbeat, estimates come every period, an RTR is answered with the estimates of its arrival,
and the watchdog idles the axis when the host stops sending torque. Generous timeouts; no
timing is asserted."""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from dob_hil.errors import DriveFault
from dob_hil.link.odrive.codec import CmdId, ODriveError
from dob_hil.link.odrive.link import OdriveDriveLink
from dob_hil.link.odrive.options import odrive_options
from firmware_sim.odrive import SimulatedOdrive

from .odrive_support import NODE, odrive_config

_channels = itertools.count()


@pytest.fixture
def pair(tmp_path: Path) -> Iterator[tuple[OdriveDriveLink, SimulatedOdrive, can.BusABC]]:
    config = odrive_config(
        tmp_path, cyclic=True, drive={"watchdog_periods": 50, "feedback_timeout_periods": 500}
    )
    channel = f"he-odrive-rt-{next(_channels)}"
    host_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    drive_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    spy = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    link = OdriveDriveLink(host_bus, config.drive, odrive_options(config), config.plant.period_ns)
    drive = SimulatedOdrive(drive_bus, config, clock="realtime")
    drive.start()
    try:
        yield link, drive, spy
    finally:
        drive.close()
        link.close()
        for bus in (host_bus, drive_bus, spy):
            bus.shutdown()


def test_enable_estimates_rtr_and_watchdog_in_real_time(
    pair: tuple[OdriveDriveLink, SimulatedOdrive, can.BusABC],
) -> None:
    link, drive, spy = pair
    link.enable(10_000_000_000)
    assert drive.enabled
    for _ in range(5):
        fb = link.receive_feedback(5_000_000_000)
        assert fb is not None and fb.enabled
        link.send_command(link.quantize((0.0,))[0], fb.seq)
    while spy.recv(0.0) is not None:
        pass
    link.send_sync()
    deadline = time.monotonic() + 10.0
    answered = False
    while time.monotonic() < deadline and not answered:
        msg = spy.recv(0.5)
        answered = (
            msg is not None
            and msg.arbitration_id == NODE << 5 | CmdId.GET_ENCODER_ESTIMATES
            and (drive.stats.rtr_answered == 1)
        )
    assert answered and drive.stats.rtr_answered == 1
    # no more torque inputs: the drive's watchdog (50 ms) idles the axis, the next heartbeat says so
    with pytest.raises(DriveFault, match="WATCHDOG_TIMER_EXPIRED"):
        while time.monotonic() < deadline + 10.0:
            link.receive_feedback(100_000_000)
    assert not drive.enabled and drive.axis_error == ODriveError.WATCHDOG_TIMER_EXPIRED
