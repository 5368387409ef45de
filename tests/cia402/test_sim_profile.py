"""The simulated CiA 402 drive as the session builds and drives it (the profile's counterpart)."""

from __future__ import annotations

import threading

import can
from sim_support import make_config, unique_channel

from dob_hil.profiles import get_profile
from firmware_sim.cia402 import SimulatedCia402Drive
from firmware_sim.truth import GroundTruth


def test_profile_builds_the_drive_and_service_never_blocks() -> None:
    channel = unique_channel()
    host = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    truths: list[GroundTruth] = []
    try:
        drive = get_profile("cia402").make_sim(bus, make_config(), "lockstep", truths.append)
        assert isinstance(drive, SimulatedCia402Drive)
        assert (drive.period_index, drive.time_ns, drive.enabled) == (0, 0, False)
        drive.start()  # nothing in lockstep
        assert drive.service() == 0  # nothing pending: returns at once
        callers = [threading.Thread(target=lambda: [drive.service() for _ in range(200)]) for _ in range(2)]
        for t in callers:  # a helper thread servicing while another calls: serialised, no error
            t.start()
        for t in callers:
            t.join()
        drive.advance_period()
        assert drive.time_ns == make_config().plant.period_ns and drive.period_index == 1
        assert len(truths) == 1 and truths[0].period_index == 1
        drive.stop()
    finally:
        host.shutdown()
        bus.shutdown()
