"""The link against a drive end on each backend: python-can ``virtual`` here, SocketCAN where it exists.

One base class, one subclass per interface (python-can's back2back_test pattern). SocketCAN needs
the kernel's AF_CAN and a ``vcan0`` device; on this machine ``socket(AF_CAN, ...)`` fails with
errno 97 (EAFNOSUPPORT), so that subclass skips, saying why.
"""

from __future__ import annotations

import errno
import os
import socket
from collections.abc import Iterator

import can
import pytest

from dob_hil.link import protocol as p
from dob_hil.link.protocol import CommandFrame, ControlFrame, ControlRequest, DriveState, Status
from dob_hil.link.unwrap import wrap_counts

from .conftest import FakeDrive, make_rig, unique_channel

SECOND_NS = 1_000_000_000


def socketcan_unavailable() -> str | None:
    """Why SocketCAN cannot be used here, or None if it can."""
    if not hasattr(socket, "AF_CAN"):
        return "SocketCAN unavailable: this Python has no socket.AF_CAN (not Linux)"
    try:
        sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except OSError as exc:
        name = errno.errorcode.get(exc.errno or 0, "?")
        return (
            f"SocketCAN unavailable: socket(AF_CAN, SOCK_RAW, CAN_RAW) fails with errno {exc.errno} ({name})"
        )
    sock.close()
    if not os.path.exists("/sys/class/net/vcan0"):
        return "SocketCAN available but no vcan0 (ip link add dev vcan0 type vcan && ip link set up vcan0)"
    return None


class LinkBackToBack:
    """The scenarios every backend must pass; subclasses say how to open two ends of one bus."""

    def open_pair(self) -> tuple[can.BusABC, can.BusABC]:
        raise NotImplementedError

    @pytest.fixture
    def ends(self) -> Iterator[tuple[can.BusABC, can.BusABC]]:
        host, drive = self.open_pair()
        yield host, drive
        host.shutdown()
        drive.shutdown()

    def test_enable_cycle_and_stop(self, ends: tuple[can.BusABC, can.BusABC]) -> None:
        rig = make_rig(*ends)
        drive: FakeDrive = rig.drive
        rig.link.request_enable()
        assert drive.received(1.0) == [(1, ControlFrame(ControlRequest.ENABLE))]
        drive.heartbeat(DriveState.ENABLED)
        rig.link.wait_enabled(SECOND_NS)
        position = 2**31 - 30
        for seq in range(4):
            drive.feedback(wrap_counts(position, 32), seq, Status.ENABLED)
            fb = rig.link.receive_feedback(SECOND_NS)
            assert fb is not None and fb.counts == (position,)
            codes, _, _ = rig.link.quantize((0.1,))
            rig.link.send_command(codes, fb.seq)
            assert drive.received(1.0) == [(1, CommandFrame(205, seq, True))]  # 0.1 A = 204.8 LSB
            position += 20
        rig.link.close()
        assert drive.received(1.0) == [
            (1, CommandFrame(0, 3, False)),
            (1, ControlFrame(ControlRequest.DISABLE)),
        ]

    def test_foreign_traffic_is_skipped(self, ends: tuple[can.BusABC, can.BusABC]) -> None:
        rig = make_rig(*ends)
        rig.drive.send(p.FrameKind.FEEDBACK, bytes(6), node_id=9)
        rig.drive.feedback(1, 0)
        fb = rig.link.receive_feedback(SECOND_NS)
        assert fb is not None and fb.counts == (1,)
        assert rig.rec.kinds()[0] == "FOREIGN_FRAME"


class TestVirtual(LinkBackToBack):
    def open_pair(self) -> tuple[can.BusABC, can.BusABC]:
        channel = unique_channel()
        return (
            can.Bus(interface="virtual", channel=channel, receive_own_messages=False),
            can.Bus(interface="virtual", channel=channel, receive_own_messages=False),
        )


@pytest.mark.skipif(socketcan_unavailable() is not None, reason=str(socketcan_unavailable()))
class TestSocketCAN(LinkBackToBack):
    def open_pair(self) -> tuple[can.BusABC, can.BusABC]:
        return (
            can.Bus(interface="socketcan", channel="vcan0", receive_own_messages=False),
            can.Bus(interface="socketcan", channel="vcan0", receive_own_messages=False),
        )
