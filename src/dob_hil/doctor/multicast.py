"""Checks for python-can's ``udp_multicast`` interface: a private port, traffic kept local."""

from __future__ import annotations

import ipaddress
import re

from dob_hil.doctor.result import Check, Status

DEFAULT_PORT = 43113  # python-can's udp_multicast default: every group on the host shares it


def port_check(port: int | None) -> Check:
    if port is None or port == DEFAULT_PORT:
        return Check(
            "udp_multicast port",
            Status.WARN,
            f"the default port {DEFAULT_PORT}: every udp_multicast bus on this host shares it, whatever "
            "the group, so another run's frames reach this one",
            "give the bus a private port: CAN_CONFIG='{\"port\": 50123}' (both processes the same)",
        )
    return Check("udp_multicast port", Status.PASS, f"private port {port}")


def group_check(channel: str | None) -> Check:
    if channel is None:
        return Check(
            "multicast group", Status.FAIL, "no channel (the multicast group) given", "-c 239.74.163.2"
        )
    try:
        addr = ipaddress.ip_address(channel)
    except ValueError:
        return Check("multicast group", Status.FAIL, f"{channel!r} is not an IP address", "-c 239.74.163.2")
    if not addr.is_multicast:
        return Check(
            "multicast group", Status.FAIL, f"{channel} is not a multicast address", "-c 239.74.163.2"
        )
    return Check("multicast group", Status.PASS, f"{channel}")


def route_check(route_text: str | None, channel: str) -> Check:
    """From ``ip route get GROUP``: which interface the frames leave on."""
    if route_text is None:
        return Check("multicast route", Status.SKIP, f"'ip route get {channel}' gave nothing")
    m = re.search(r"\bdev\s+(\S+)", route_text)
    dev = m.group(1) if m else "?"
    if dev == "lo":
        return Check("multicast route", Status.PASS, f"{channel} routes to lo: traffic stays on this machine")
    return Check(
        "multicast route",
        Status.WARN,
        f"{channel} leaves on {dev} (TTL 1): every host on that network segment can see and inject frames",
        "sudo ip route add 224.0.0.0/4 dev lo (or run both sides in a private network namespace)",
    )


def msgpack_check() -> Check:
    try:
        import msgpack  # noqa: F401
    except ImportError:
        return Check(
            "msgpack", Status.FAIL, "python-can's udp_multicast needs msgpack", "pip install msgpack"
        )
    return Check("msgpack", Status.PASS, "installed")
