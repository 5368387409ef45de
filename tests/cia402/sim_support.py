"""Test support for the simulated CiA 402 drive: configs, a raw-frame rig and a canopen master rig.

The master rig is the ``canopen`` package acting as an independent CANopen master (its own SDO
client, PDO maps, NMT master, BaseNode402) over python-can ``virtual``, with the drive in lockstep
serviced by a thread of its own (as a real drive runs beside the master).
"""

from __future__ import annotations

import itertools
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import canopen

from dob_hil.config import Config, parse_config
from firmware_sim.cia402 import SimulatedCia402Drive
from firmware_sim.cia402.objects import shipped_eds
from firmware_sim.truth import GroundTruth

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

REPO_ROOT = Path(__file__).resolve().parents[2]
SCENARIO = REPO_ROOT / "src" / "dob_hil" / "scenarios" / "paper-step-cia402.toml"
NODE = 1
TIMEOUT_S = 10.0  # generous: the machine is loaded; nothing here waits for it to pass

_channels = itertools.count()


def unique_channel() -> str:
    return f"cia402-sim-test-{os.getpid()}-{next(_channels)}"


def scenario_data(**sections: dict[str, Any]) -> dict[str, Any]:
    """paper-step-cia402 with ``sections`` merged in (a value of None deletes the key)."""
    data = tomllib.loads(SCENARIO.read_text(encoding="utf-8"))
    for name, values in sections.items():
        table = data
        for part in name.split("."):
            table = table.setdefault(part, {})
        for key, value in values.items():
            if value is None:
                table.pop(key, None)
            else:
                table[key] = value
    return data


def make_config(**sections: dict[str, Any]) -> Config:
    return parse_config(scenario_data(**sections))


def sdo_request(cs: int, index: int, subindex: int, payload: bytes = b"") -> bytes:
    return bytes([cs]) + index.to_bytes(2, "little") + bytes([subindex]) + payload.ljust(4, b"\x00")


@dataclass
class RawRig:
    """The drive in lockstep and a host end that sends and reads raw frames."""

    host: can.BusABC
    drive: SimulatedCia402Drive
    truths: list[GroundTruth] = field(default_factory=list)
    boot_frames: list[can.Message] = field(default_factory=list)  # what the drive sent on power-on

    def send(self, can_id: int, data: bytes = b"") -> None:
        self.host.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))

    def exchange(self, can_id: int, data: bytes = b"") -> list[can.Message]:
        """Send one frame, let the drive act on it, return every frame the drive sent."""
        self.send(can_id, data)
        self.drive.service()
        return self.drain()

    def drain(self) -> list[can.Message]:
        out = []
        while (msg := self.host.recv(0.0)) is not None:
            out.append(msg)
        return out

    def sdo(self, request: bytes) -> bytes:
        """One SDO request; the drive's (single) response payload."""
        replies = [m for m in self.exchange(0x600 + NODE, request) if m.arbitration_id == 0x580 + NODE]
        assert len(replies) == 1, replies
        return bytes(replies[0].data)

    def write(self, index: int, subindex: int, value: int, size: int) -> bytes:
        cs = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
        signed = value < 0
        return self.sdo(sdo_request(cs, index, subindex, value.to_bytes(size, "little", signed=signed)))

    def sync(self) -> list[can.Message]:
        return self.exchange(0x80)

    def enable(self, *, start: bool = True) -> None:
        """Mode 10, NMT start, then shutdown / switch on / enable operation by SDO."""
        assert self.write(0x6060, 0, 10, 1)[0] == 0x60
        if start:
            self.exchange(0x000, bytes([0x01, NODE]))
        for cw in (0x06, 0x07, 0x0F):
            assert self.write(0x6040, 0, cw, 2)[0] == 0x60


@contextmanager
def raw_rig(config: Config | None = None) -> Iterator[RawRig]:
    channel = unique_channel()
    host = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    truths: list[GroundTruth] = []
    try:
        drive = SimulatedCia402Drive(bus, config or make_config(), truth_sink=truths.append)
        rig = RawRig(host, drive, truths)
        rig.boot_frames = rig.drain()
        yield rig
    finally:
        host.shutdown()
        bus.shutdown()


class _Capture(can.Listener):
    def __init__(self, frames: list[can.Message]) -> None:
        self.frames = frames

    def on_message_received(self, msg: can.Message) -> None:
        self.frames.append(msg)


class Servicer:
    """Keeps a lockstep drive serviced from a thread of its own while a blocking master runs."""

    def __init__(self, drive: SimulatedCia402Drive) -> None:
        self.drive = drive
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="cia402-servicer", daemon=True)

    def _run(self) -> None:
        try:
            while not self._stop.wait(0.0002):
                self.drive.service()
        except BaseException as exc:
            self._error = exc

    def __enter__(self) -> Servicer:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        if self._error is not None:
            raise self._error


@dataclass
class MasterRig:
    network: canopen.Network
    node: canopen.BaseNode402
    drive: SimulatedCia402Drive
    truths: list[GroundTruth]
    emcys: list[canopen.emcy.EmcyError]
    heartbeats: list[int]
    frames: list[can.Message]  # every frame the master received

    def wait_for(self, condition: Callable[[], bool], what: str) -> None:
        deadline = time.monotonic() + TIMEOUT_S
        while not condition():
            assert time.monotonic() < deadline, f"timed out waiting for {what}"
            time.sleep(0.001)


@contextmanager
def master_rig(config: Config | None = None) -> Iterator[MasterRig]:
    """canopen master (Notifier thread) + the drive in lockstep serviced by a thread."""
    channel = unique_channel()
    bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    network = canopen.Network()
    frames: list[can.Message] = []
    network.listeners.append(_Capture(frames))
    network.connect(interface="virtual", channel=channel, receive_own_messages=False)
    node = canopen.BaseNode402(NODE, str(shipped_eds()))
    node.TIMEOUT_SWITCH_STATE_FINAL = TIMEOUT_S
    node.TIMEOUT_SWITCH_STATE_SINGLE = TIMEOUT_S
    node.TIMEOUT_CHECK_TPDO = TIMEOUT_S
    node.TIMEOUT_RESET_FAULT = TIMEOUT_S
    node.TIMEOUT_SWITCH_OP_MODE = TIMEOUT_S
    node.sdo.RESPONSE_TIMEOUT = TIMEOUT_S
    network.add_node(node)
    emcys: list[canopen.emcy.EmcyError] = []
    heartbeats: list[int] = []
    node.emcy.add_callback(emcys.append)
    node.nmt.add_heartbeat_callback(heartbeats.append)
    truths: list[GroundTruth] = []
    drive = SimulatedCia402Drive(bus, config or make_config(), truth_sink=truths.append)
    try:
        with Servicer(drive):
            yield MasterRig(network, node, drive, truths, emcys, heartbeats, frames)
    finally:
        network.sync.stop()
        network.disconnect()
        bus.shutdown()
