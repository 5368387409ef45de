"""The host-clocked (RTR-triggered) mode, ready for a host-clocked runner: with
``encoder_msg_rate_ms = 0`` the drive sends no cyclic estimates, the host's RTR
Get_Encoder_Estimates (``send_sync()`` / ``send_trigger()``) is each sample's trigger and its
index the sequence number; the lockstep drive advances one period per trigger. The shipped
profile is host-clocked: its descriptor refuses cyclic estimates, naming the setting."""

from __future__ import annotations

from pathlib import Path

import pytest

from dob_hil.config import Config
from dob_hil.errors import ConfigError
from dob_hil.link.base import LinkEventKind
from dob_hil.link.odrive.codec import CmdId
from dob_hil.link.odrive.link import OdriveDriveLink
from dob_hil.link.odrive.options import odrive_options

from .odrive_support import make_rig, odrive_config


def rtr_config(tmp_path: Path) -> Config:
    return odrive_config(tmp_path, odrive={"encoder_msg_rate_ms": 0})


def test_rtr_triggers_clock_the_lockstep_drive(tmp_path: Path) -> None:
    config = rtr_config(tmp_path)
    rig = make_rig(config)
    try:
        # the rig's link was built for the drive-clocked check; rebuild it for RTR mode
        rig.link = OdriveDriveLink(rig.host_bus, config.drive, odrive_options(config, host_clocked=True),
                                   config.plant.period_ns, event_hook=rig.events.append)  # fmt: skip
        rig.link.enable_lockstep(rig.drive.service)
        for k in range(300):  # what a host-clocked lockstep runner does: trigger, service, receive
            rig.link.send_trigger()
            rig.drive.service()
            fb = rig.link.receive_feedback(0)
            assert fb is not None and fb.seq == k % 256 and rig.drive.period_index == k
            rig.link.send_command(rig.link.quantize((0.1,))[0], fb.seq)
        assert rig.drive.stats.rtr_answered == 300
        assert not rig.events or {e.kind for e in rig.events} == {LinkEventKind.DRIVE_STATE}
    finally:
        rig.close()


def test_unasked_estimates_are_stale_in_rtr_mode(tmp_path: Path) -> None:
    config = rtr_config(tmp_path)
    rig = make_rig(config)
    try:
        link = OdriveDriveLink(rig.host_bus, config.drive, odrive_options(config, host_clocked=True),
                               config.plant.period_ns, event_hook=rig.events.append)  # fmt: skip
        rig.inject(CmdId.GET_ENCODER_ESTIMATES, bytes(8))
        assert link.receive_feedback(0) is None
        assert [e.kind for e in rig.events] == [LinkEventKind.STALE_FEEDBACK]
        link.send_sync()
        rig.inject(CmdId.GET_ENCODER_ESTIMATES, bytes(8))
        rig.inject(CmdId.GET_ENCODER_ESTIMATES, bytes(8))  # a second answer to the same trigger
        fb = link.receive_feedback(0)
        assert fb is not None and fb.seq == 0
        assert link.receive_feedback(0) is None and link.stats.stale_feedback == 2
    finally:
        rig.close()


def test_each_clocking_refuses_the_others_rate(tmp_path: Path) -> None:
    config = rtr_config(tmp_path)
    with pytest.raises(
        ConfigError, match=r"encoder_msg_rate_ms: 0 \(RTR-triggered estimates\) needs a host-clocked"
    ):
        odrive_options(config, host_clocked=False)
    with pytest.raises(ConfigError, match=r"encoder_msg_rate_ms: 1 ms: the host's RTR triggers each sample"):
        odrive_options(odrive_config(tmp_path, name="cyclic", cyclic=True), host_clocked=True)
