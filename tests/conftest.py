"""Shared test support modules live in tests/support (importable as top-level modules).

Every test process (each pytest-xdist worker, or pytest itself without xdist) moves into a private
network namespace at session start, so that python-can ``udp_multicast`` traffic of the
cross-process tests stays on this process's own loopback (see ``tests/support/udp_isolation.py``).
Tests get a private group and port from the ``udp_channel`` fixture.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

_SUPPORT = str(Path(__file__).resolve().parent / "support")
if _SUPPORT not in sys.path:
    sys.path.insert(0, _SUPPORT)

from udp_isolation import UdpChannel, enter_private_network, private_udp_channel  # noqa: E402


@pytest.fixture(scope="session", autouse=True)
def _private_network() -> None:
    """Set up once per test process, in the thread that runs the tests (a namespace is per thread;
    the processes a test starts inherit it). Unavailable: the cross-process tests skip, saying why."""
    enter_private_network()


@pytest.fixture
def udp_channel() -> Iterator[UdpChannel]:
    """A private udp_multicast group and port (``CAN_CONFIG`` for this process and its children)."""
    with private_udp_channel() as chan:
        yield chan
