"""Fixtures: a python-can ``virtual`` bus pair (host end, drive end) on a channel of its own."""

from __future__ import annotations

from collections.abc import Iterator

import can
import pytest
from fs_support import unique_channel


@pytest.fixture
def bus_pair() -> Iterator[tuple[can.BusABC, can.BusABC]]:
    channel = unique_channel()
    host = can.Bus(interface="virtual", channel=channel)
    drive = can.Bus(interface="virtual", channel=channel)
    try:
        yield host, drive
    finally:
        host.shutdown()
        drive.shutdown()
