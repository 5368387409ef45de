"""Shared fixtures: a python-can ``virtual`` bus pair and a scripted fake drive on its far end."""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator
from dataclasses import dataclass, field

import can
import pytest

from dob_hil.config import DriveConfig
from dob_hil.link import protocol
from dob_hil.link.base import LinkEvent
from dob_hil.link.native import NativeDriveLink
from dob_hil.link.protocol import FrameKind, frame_id

_channels = itertools.count()


def unique_channel() -> str:
    return f"dob-hil-test-{os.getpid()}-{next(_channels)}"


class FakeDrive:
    """The drive end of the bus, scripted by the test: it sends what it is told to."""

    def __init__(self, bus: can.BusABC, node_id: int = 1) -> None:
        self.bus = bus
        self.node_id = node_id

    def send(self, kind: FrameKind, payload: bytes, node_id: int | None = None) -> None:
        node = self.node_id if node_id is None else node_id
        self.bus.send(can.Message(arbitration_id=frame_id(kind, node), is_extended_id=False, data=payload))

    def feedback(self, counts: int, seq: int, status: protocol.Status = protocol.Status.ENABLED) -> None:
        self.send(FrameKind.FEEDBACK, protocol.encode_feedback(protocol.FeedbackFrame(counts, seq, status)))

    def heartbeat(self, state: protocol.DriveState) -> None:
        self.send(FrameKind.HEARTBEAT, protocol.encode_heartbeat(protocol.HeartbeatFrame(state)))

    def fault(self, code: protocol.FaultCode, info: int = 0) -> None:
        self.send(FrameKind.FAULT, protocol.encode_fault(protocol.FaultFrame(code, info)))

    def raw(self, msg: can.Message) -> None:
        self.bus.send(msg)

    def received(self, timeout_s: float = 0.0) -> list[tuple[int, protocol.Frame]]:
        """Every frame that reached the drive so far, decoded: [(node, frame), ...]."""
        out = []
        while (msg := self.bus.recv(timeout_s)) is not None:
            out.append(protocol.decode(msg.arbitration_id, msg.data))
            timeout_s = 0.0
        return out


@dataclass
class Recorder:
    frames: list[tuple[can.Message, bool]] = field(default_factory=list)
    events: list[LinkEvent] = field(default_factory=list)

    def frame(self, msg: can.Message, is_rx: bool) -> None:
        self.frames.append((msg, is_rx))

    def event(self, ev: LinkEvent) -> None:
        self.events.append(ev)

    def kinds(self) -> list[str]:
        return [ev.kind.name for ev in self.events]


class FakeClock:
    """A clock that advances 1000 ns per reading, so every timestamp is distinct and known."""

    def __init__(self) -> None:
        self.now_ns = 0

    def __call__(self) -> int:
        self.now_ns += 1000
        return self.now_ns


@dataclass
class Rig:
    host: can.BusABC
    drive: FakeDrive
    link: NativeDriveLink
    rec: Recorder
    clock: FakeClock


@pytest.fixture
def bus_pair() -> Iterator[tuple[can.BusABC, can.BusABC]]:
    channel = unique_channel()
    host = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    drive = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    yield host, drive
    host.shutdown()
    drive.shutdown()


def make_rig(host: can.BusABC, drive_bus: can.BusABC, config: DriveConfig | None = None, **kw: object) -> Rig:
    rec = Recorder()
    clock = FakeClock()
    cfg = config if config is not None else DriveConfig()
    link = NativeDriveLink(
        host,
        cfg,
        frame_hook=rec.frame,
        event_hook=rec.event,
        clock_ns=clock,
        **kw,  # type: ignore[arg-type]
    )
    return Rig(host, FakeDrive(drive_bus, cfg.node_id), link, rec, clock)


@pytest.fixture
def rig(bus_pair: tuple[can.BusABC, can.BusABC]) -> Rig:
    return make_rig(*bus_pair)
