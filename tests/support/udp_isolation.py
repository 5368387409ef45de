"""Isolation of python-can ``udp_multicast`` traffic for the cross-process tests.

python-can binds every ``udp_multicast`` bus to ``("", port)`` (43113 by default), so a socket
receives every group's datagrams on that port, from every process of the host: a different group
address is no isolation, and another run's drive leaks frames into a test. Two measures, both
applied to every cross-process test:

- a private network namespace per test process (per pytest-xdist worker, set up once at session
  start by ``tests/conftest.py``): ``unshare(CLONE_NEWNET)`` through libc, ``lo`` up and
  ``224.0.0.0/4`` routed to ``lo``. Child processes (``python -m firmware_sim``, ``dob-hil run``)
  inherit it. Python 3.11 has no ``os.unshare``, hence ctypes. Needs root (or CAP_SYS_ADMIN) and
  iproute2's ``ip``;
- a private UDP port per test, given to python-can through its ``CAN_CONFIG`` environment variable
  (read by ``can.Bus`` in this process and in every child started after it is set) or its ``port``
  bus option.

Where the namespace cannot be set up, :func:`require_private_network` skips the test and says why.
"""

from __future__ import annotations

import ctypes
import json
import os
import random
import shutil
import socket
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import pytest

CLONE_NEWNET = 0x40000000
GROUP_PREFIX = "239.74.163."

_state: dict[str, str | None] = {}  # "reason": None once set up, else why it could not be


def _run_ip(*args: str) -> None:
    ip = shutil.which("ip")
    if ip is None:
        raise OSError("iproute2's `ip` command is not installed")
    done = subprocess.run([ip, *args], capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise OSError(f"`ip {' '.join(args)}` failed: {done.stderr.strip()}")


def enter_private_network() -> str | None:
    """Move this thread (and the processes it starts later) into a new network namespace with only
    a loopback that carries multicast. Returns None on success, else the reason it is unavailable.
    Idempotent: the first call decides."""
    if "reason" in _state:
        return _state["reason"]
    reason: str | None = None
    if shutil.which("ip") is None:
        reason = "no private network namespace: iproute2's `ip` command is not installed"
    elif os.geteuid() != 0:
        reason = "no private network namespace: unshare(CLONE_NEWNET) needs root (or CAP_SYS_ADMIN)"
    else:
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            if libc.unshare(CLONE_NEWNET) != 0:
                err = ctypes.get_errno()
                raise OSError(err, f"unshare(CLONE_NEWNET): {os.strerror(err)}")
            _run_ip("link", "set", "lo", "up")
            _run_ip("route", "add", "224.0.0.0/4", "dev", "lo")
        except (OSError, AttributeError) as exc:
            reason = f"no private network namespace: {exc}"
    _state["reason"] = reason
    return reason


def require_private_network() -> None:
    """Skip the calling test, with the reason, unless this process runs in its private namespace."""
    reason = _state.get("reason", "no private network namespace: not set up (tests/conftest.py)")
    if reason is not None:
        pytest.skip(f"cross-process udp_multicast test: {reason}")


def free_udp_port() -> int:
    """A UDP port nobody in this namespace has bound (the kernel's choice)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("", 0))
        port: int = s.getsockname()[1]
    return port


@dataclass(frozen=True)
class UdpChannel:
    """A private udp_multicast channel: the group address and the port."""

    channel: str
    port: int

    @property
    def bus_kwargs(self) -> dict[str, object]:
        """Keyword arguments for ``can.Bus`` in this process."""
        return {"interface": "udp_multicast", "channel": self.channel, "port": self.port}


@contextmanager
def private_udp_channel() -> Iterator[UdpChannel]:
    """Skip unless isolated; then a private group and port, the port set in ``CAN_CONFIG`` for this
    process and its children for the duration (restored afterwards)."""
    require_private_network()
    chan = UdpChannel(f"{GROUP_PREFIX}{random.randint(10, 250)}", free_udp_port())
    old = os.environ.get("CAN_CONFIG")
    config = json.loads(old or "{}")
    config["port"] = chan.port
    os.environ["CAN_CONFIG"] = json.dumps(config)
    try:
        yield chan
    finally:
        if old is None:
            os.environ.pop("CAN_CONFIG", None)
        else:
            os.environ["CAN_CONFIG"] = old
