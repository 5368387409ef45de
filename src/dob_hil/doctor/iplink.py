"""Parse ``ip -details -statistics link show DEV`` for a SocketCAN interface (iproute2's text).

The parts ``doctor`` needs: flags and operational state, the transmit queue length, the CAN
controller state with its error counters, ``restart-ms``, the nominal and data bit rates, the
controller's error statistics (re-started, bus-errors, arbit-lost, error-warn, error-pass, bus-off)
and the RX/TX error and drop counters. Anything absent stays None (a ``vcan`` has no bit timing).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

_HEADER = re.compile(r"^\s*\d+:\s+(?P<name>[^:@\s]+)(?:@\S+)?:\s+<(?P<flags>[^>]*)>(?P<rest>.*)$")
_QLEN = re.compile(r"\bqlen\s+(\d+)")
_STATE = re.compile(r"\bstate\s+(\S+)")
_CAN = re.compile(
    r"^\s*can\s+(?:<(?P<ctrl>[^>]*)>\s+)?state\s+(?P<state>[A-Z-]+)"
    r"(?:\s+\(berr-counter\s+tx\s+(?P<tx>\d+)\s+rx\s+(?P<rx>\d+)\))?"
    r"(?:\s+restart-ms\s+(?P<restart>\d+))?"
)
_BITRATE = re.compile(r"^\s*bitrate\s+(\d+)")
_DBITRATE = re.compile(r"^\s*dbitrate\s+(\d+)")
_CTRL_STATS = ("re-started", "bus-errors", "arbit-lost", "error-warn", "error-pass", "bus-off")


@dataclass
class CanLink:
    name: str
    flags: tuple[str, ...] = ()
    operstate: str | None = None
    txqueuelen: int | None = None
    kind: str | None = None  # "can" (a controller) or "vcan"
    controller_mode: tuple[str, ...] = ()  # e.g. FD, LOOPBACK, TRIPLE-SAMPLING
    can_state: str | None = None  # ERROR-ACTIVE, ERROR-WARNING, ERROR-PASSIVE, BUS-OFF, STOPPED
    tx_errors: int | None = None  # berr-counter
    rx_errors: int | None = None
    restart_ms: int | None = None
    bitrate_bps: int | None = None
    data_bitrate_bps: int | None = None
    controller_stats: dict[str, int] = field(default_factory=dict)
    rx_stats: dict[str, int] = field(default_factory=dict)
    tx_stats: dict[str, int] = field(default_factory=dict)

    @property
    def up(self) -> bool:
        return "UP" in self.flags

    @property
    def fd(self) -> bool:
        return "FD" in self.controller_mode or self.data_bitrate_bps is not None


class IpLinkParseError(ValueError):
    pass


def _table(header: str, values: str) -> dict[str, int]:
    names = header.split()
    nums = values.split()
    out: dict[str, int] = {}
    for name, value in zip(names, nums, strict=False):
        if value.isdigit():
            out[name] = int(value)
    return out


def parse_ip_link(text: str) -> CanLink:
    """The first interface in ``text`` (the output of ``ip -details -statistics link show DEV``)."""
    lines = text.splitlines()
    start = next((i for i, line in enumerate(lines) if _HEADER.match(line)), None)
    if start is None:
        raise IpLinkParseError("no interface header ('N: name: <FLAGS> ...') in the ip link output")
    head = _HEADER.match(lines[start])
    assert head is not None
    link = CanLink(name=head["name"], flags=tuple(f for f in head["flags"].split(",") if f))
    rest = head["rest"]
    if (m := _QLEN.search(rest)) is not None:
        link.txqueuelen = int(m.group(1))
    if (m := _STATE.search(rest)) is not None:
        link.operstate = m.group(1)
    body = lines[start + 1 :]
    i = 0
    while i < len(body):
        line = body[i]
        if _HEADER.match(line):
            break  # the next interface
        stripped = line.strip()
        if (m := _CAN.match(line)) is not None:
            link.kind = "can"
            link.can_state = m["state"]
            link.controller_mode = tuple(c for c in (m["ctrl"] or "").split(",") if c)
            if m["tx"] is not None:
                link.tx_errors, link.rx_errors = int(m["tx"]), int(m["rx"])
            if m["restart"] is not None:
                link.restart_ms = int(m["restart"])
        elif stripped.startswith("vcan"):
            link.kind = "vcan"
        elif (m := _BITRATE.match(line)) is not None:
            link.bitrate_bps = int(m.group(1))
        elif (m := _DBITRATE.match(line)) is not None:
            link.data_bitrate_bps = int(m.group(1))
        elif stripped.split()[:1] == ["re-started"] and i + 1 < len(body):
            link.controller_stats = _table(stripped, body[i + 1])
            i += 1
        elif stripped.startswith("RX:") and i + 1 < len(body):
            link.rx_stats = _table(stripped[3:], body[i + 1])
            i += 1
        elif stripped.startswith("TX:") and i + 1 < len(body):
            link.tx_stats = _table(stripped[3:], body[i + 1])
            i += 1
        i += 1
    if link.kind is None and "link/can" in text:
        link.kind = "can"
    return link


CONTROLLER_STAT_NAMES = _CTRL_STATS
