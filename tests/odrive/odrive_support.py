"""Shared helpers of the ODrive tests: configs, a host link and a lockstep simulated ODrive on one
virtual bus, and the frames on it."""

from __future__ import annotations

import itertools
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from dob_hil.config import Config, load_config
from dob_hil.link.base import LinkEvent
from dob_hil.link.odrive import codec
from dob_hil.link.odrive.codec import CmdId
from dob_hil.link.odrive.link import OdriveDriveLink
from dob_hil.link.odrive.options import odrive_options
from dob_hil.scenarios import scenario_path
from firmware_sim.odrive import SimulatedOdrive

NODE = 1
_channels = itertools.count()


def odrive_text(*, drive: dict[str, Any] | None = None, odrive: dict[str, Any] | None = None,
                extra: str = "", cyclic: bool = False) -> str:  # fmt: skip
    """paper-step-odrive's TOML with ``[drive]`` and ``[drive.odrive]`` keys replaced (or added);
    ``cyclic``: the drive-clocked variant (cyclic estimates every period) for the link's and the
    simulated drive's own tests (the shipped, host-clocked profile refuses it)."""
    text = scenario_path("paper-step-odrive").read_text()
    if cyclic:
        odrive = {"encoder_msg_rate_ms": 1, **(odrive or {})}
    for table, changes in (("[drive]", drive or {}), ("[drive.odrive]", odrive or {})):
        head, sep, tail = text.partition(f"\n{table}\n")
        body, nxt, rest = tail.partition("\n[")
        for key, value in changes.items():
            body, n = re.subn(rf"(?m)^{key} = .*$", f"{key} = {toml(value)}", body)
            if n == 0:
                body = f"{key} = {toml(value)}\n" + body
        text = head + sep + body + nxt + rest
    return text + extra


def odrive_config(tmp_path: Path, name: str = "odrive", **kw: Any) -> Config:
    """See :func:`odrive_text`."""
    path = tmp_path / f"{name}.toml"
    path.write_text(odrive_text(**kw))
    return load_config(path)


def toml(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    return repr(value)


@dataclass
class Rig:
    """A host link and a lockstep simulated ODrive on one virtual bus, with a spy on the bus."""

    config: Config
    link: OdriveDriveLink
    drive: SimulatedOdrive
    host_bus: can.BusABC
    drive_bus: can.BusABC
    spy: can.BusABC
    events: list[LinkEvent] = field(default_factory=list)

    def close(self) -> None:
        self.link.close()
        for bus in (self.host_bus, self.drive_bus, self.spy):
            bus.shutdown()

    def sent(self) -> list[can.Message]:
        """Every frame on the bus so far (read from the spy)."""
        out = []
        while (msg := self.spy.recv(0.0)) is not None:
            out.append(msg)
        return out

    def inject(self, cmd: CmdId, data: bytes, **kw: Any) -> None:
        """A frame as the drive would send it (from the drive's bus end)."""
        self.drive_bus.send(can.Message(arbitration_id=codec.arbitration_id(NODE, cmd), data=data,
                                        is_extended_id=False, **kw))  # fmt: skip


def make_rig(config: Config) -> Rig:
    channel = f"he-odrive-test-{next(_channels)}"
    host_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    drive_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    spy = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    events: list[LinkEvent] = []
    link = OdriveDriveLink(host_bus, config.drive, odrive_options(config), config.plant.period_ns,
                           event_hook=events.append)  # fmt: skip
    drive = SimulatedOdrive(drive_bus, config)
    return Rig(config, link, drive, host_bus, drive_bus, spy, events)


def tracking_rms(data: Any, from_s: float = 0.1) -> float:
    """RMS of reference minus the simulated drive's *true* position, over samples after ``from_s``."""
    import numpy as np

    s, t = data.samples, data.truth
    by_period = {int(p): i for i, p in enumerate(t["period_index"])}
    idx = np.array([by_period[int(k)] for k in s["seq"]])
    window = s["time_ns"] >= from_s * 1e9
    err = s["x_ref"][window, 0] - t["state"][idx[window], 0]
    return float(np.sqrt(np.mean(err**2)))
