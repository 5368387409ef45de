"""``dob-hil doctor``: check the bus and the host before a real-time run.

Every check reports pass, warn, fail or skip with what it saw and, where something needs fixing,
the command that fixes it. SocketCAN checks read ``ip -details -statistics link show DEV`` (and
``ethtool -T DEV`` for timestamps); where the kernel has no SocketCAN they are skipped with that
reason and the rest still runs.
"""

from __future__ import annotations

from dataclasses import dataclass

from dob_hil.doctor import host, multicast, socketcan
from dob_hil.doctor.iplink import IpLinkParseError, parse_ip_link
from dob_hil.doctor.result import Check, Status

__all__ = ["BusTarget", "Check", "Status", "run_doctor"]


@dataclass(frozen=True)
class BusTarget:
    interface: str | None
    channel: str | None
    bitrate_bps: int | None = None  # what the config (or -b) expects; None: not checked
    data_bitrate_bps: int | None = None
    port: int | None = None  # udp_multicast


def run_doctor(
    target: BusTarget, *, ip_link_text: str | None = None, ethtool_text: str | None = None
) -> list[Check]:
    """All checks for ``target``; ``ip_link_text``/``ethtool_text`` stand in for running the tools
    (recorded output of another machine's interface)."""
    checks: list[Check] = []
    if target.interface == "socketcan" or ip_link_text is not None:
        checks += _socketcan_checks(target, ip_link_text, ethtool_text)
    elif target.interface == "udp_multicast":
        checks += _multicast_checks(target)
    elif target.interface is None:
        checks.append(
            Check(
                "interface",
                Status.WARN,
                "no interface given and none in python-can's config: checking the host only",
                "dob-hil doctor -i socketcan -c can0 (or -i udp_multicast -c GROUP)",
            )
        )
    else:
        checks.append(
            Check("interface", Status.SKIP, f"no checks for python-can interface {target.interface!r} yet")
        )
    checks += [host.sched_fifo_permission(), host.memory_lock(), host.cpu_governor(), host.isolated_cpus(),
               host.rt_throttling()]  # fmt: skip
    return checks


def _socketcan_checks(target: BusTarget, ip_link_text: str | None, ethtool_text: str | None) -> list[Check]:
    dev = target.channel or "can0"
    checks: list[Check] = []
    if ip_link_text is None:
        support = host.socketcan_support()
        checks.append(support)
        if support.status is not Status.PASS:
            return checks
        ip_link_text = host.run_tool(["ip", "-details", "-statistics", "link", "show", "dev", dev])
        if ip_link_text is None:
            checks.append(
                Check(
                    "interface exists",
                    Status.FAIL,
                    f"no network interface {dev!r} (ip link show dev {dev} failed)",
                    f"check the adapter is plugged in and its driver loaded (ip link show type can); "
                    f"for a virtual one: sudo ip link add dev {dev} type vcan",
                )
            )
            return checks
        ethtool_text = host.run_tool(["ethtool", "-T", dev])
    try:
        link = parse_ip_link(ip_link_text)
    except IpLinkParseError as exc:
        return [*checks, Check("interface exists", Status.FAIL, f"cannot read the ip link output: {exc}")]
    checks.append(Check("interface exists", Status.PASS, f"{link.name} ({link.kind or 'unknown kind'})"))
    checks += socketcan.check_link(
        link, bitrate_bps=target.bitrate_bps, data_bitrate_bps=target.data_bitrate_bps
    )
    if link.kind == "can":
        checks.append(host.hardware_timestamps(ethtool_text, link.name))
    return checks


def _multicast_checks(target: BusTarget) -> list[Check]:
    checks = [
        multicast.msgpack_check(),
        multicast.group_check(target.channel),
        multicast.port_check(target.port),
    ]
    if checks[1].status is Status.PASS and target.channel is not None:
        checks.append(
            multicast.route_check(host.run_tool(["ip", "route", "get", target.channel]), target.channel)
        )
    return checks
