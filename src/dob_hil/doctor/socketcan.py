"""SocketCAN checks from a parsed ``ip -details -statistics link`` (see :mod:`.iplink`)."""

from __future__ import annotations

from dob_hil.doctor.iplink import CanLink
from dob_hil.doctor.result import Check, Status

MIN_TXQUEUELEN = 100  # python-can's send fails with ENOBUFS ("No buffer space available") at 10 under load
STATE_STATUS = {
    "ERROR-ACTIVE": Status.PASS,
    "ERROR-WARNING": Status.WARN,
    "ERROR-PASSIVE": Status.WARN,
    "BUS-OFF": Status.FAIL,
    "STOPPED": Status.FAIL,
    "SLEEPING": Status.FAIL,
}


def _type_cmd(dev: str, what: str) -> str:
    return (
        f"sudo ip link set {dev} down && sudo ip link set {dev} type can {what} && sudo ip link set {dev} up"
    )


def check_link(link: CanLink, *, bitrate_bps: int | None, data_bitrate_bps: int | None = None) -> list[Check]:
    """Every check that applies to ``link`` against the expected bit rates (None: not checked)."""
    dev = link.name
    checks: list[Check] = []
    if link.up:
        checks.append(Check("interface up", Status.PASS, f"{dev} is UP ({link.operstate or 'state ?'})"))
    else:
        checks.append(Check("interface up", Status.FAIL, f"{dev} is not UP", f"sudo ip link set {dev} up"))
    if link.kind == "vcan":
        checks.append(
            Check("bus", Status.WARN, f"{dev} is a virtual CAN (vcan): no drive, no bit timing, no errors")
        )
    checks.append(_bitrate(link, bitrate_bps, data_bitrate_bps))
    checks.append(_txqueuelen(link))
    if link.kind == "can":
        checks.append(_restart_ms(link))
        checks.append(_state(link))
        checks.append(_error_history(link))
    return checks


def _bitrate(link: CanLink, bitrate_bps: int | None, data_bitrate_bps: int | None) -> Check:
    dev = link.name
    if link.kind == "vcan":
        return Check("bitrate", Status.SKIP, "a vcan has no bit timing")
    if link.bitrate_bps is None:
        return Check(
            "bitrate",
            Status.FAIL,
            f"{dev} reports no bitrate (not configured)",
            _type_cmd(dev, f"bitrate {bitrate_bps or 1000000}"),
        )
    if bitrate_bps is not None and link.bitrate_bps != bitrate_bps:
        return Check(
            "bitrate",
            Status.FAIL,
            f"{dev} runs at {link.bitrate_bps} bit/s, the config expects {bitrate_bps}",
            _type_cmd(dev, f"bitrate {bitrate_bps}"),
        )
    detail = f"{link.bitrate_bps} bit/s"
    if data_bitrate_bps is not None:
        if link.data_bitrate_bps != data_bitrate_bps:
            return Check(
                "bitrate",
                Status.FAIL,
                f"{dev} data bitrate {link.data_bitrate_bps} bit/s, the config expects {data_bitrate_bps}",
                _type_cmd(dev, f"bitrate {link.bitrate_bps} dbitrate {data_bitrate_bps} fd on"),
            )
        detail += f", data {link.data_bitrate_bps} bit/s (CAN FD)"
    elif link.fd:
        detail += f", CAN FD on (data {link.data_bitrate_bps} bit/s)"
    return Check("bitrate", Status.PASS, detail + (" as configured" if bitrate_bps else ""))


def _txqueuelen(link: CanLink) -> Check:
    dev = link.name
    fix = f"sudo ip link set {dev} txqueuelen 1000"
    if link.txqueuelen is None:
        return Check("txqueuelen", Status.WARN, f"{dev}: queue length not reported", fix)
    if link.txqueuelen < MIN_TXQUEUELEN:
        return Check(
            "txqueuelen",
            Status.WARN,
            f"{dev}: txqueuelen {link.txqueuelen}; sends fail with 'No buffer space available' "
            f"under load below ~{MIN_TXQUEUELEN}",
            fix,
        )
    return Check("txqueuelen", Status.PASS, f"{dev}: txqueuelen {link.txqueuelen}")


def _restart_ms(link: CanLink) -> Check:
    dev = link.name
    fix = _type_cmd(dev, "restart-ms 100")
    if link.restart_ms is None:
        return Check("restart-ms", Status.WARN, f"{dev}: restart-ms not reported", fix)
    if link.restart_ms == 0:
        return Check(
            "restart-ms",
            Status.WARN,
            f"{dev}: restart-ms 0: after a bus-off the controller stays off until restarted by hand",
            fix,
        )
    return Check("restart-ms", Status.PASS, f"{dev}: automatic bus-off recovery after {link.restart_ms} ms")


def _state(link: CanLink) -> Check:
    dev = link.name
    state = link.can_state or "unknown"
    status = STATE_STATUS.get(state, Status.WARN)
    counters = "" if link.tx_errors is None else f" (error counters tx {link.tx_errors} rx {link.rx_errors})"
    fix = ""
    if status is not Status.PASS:
        fix = (
            f"check termination (120 ohm at both ends), wiring and that every node uses the same bitrate; "
            f"then: sudo ip link set {dev} down && sudo ip link set {dev} up"
        )
    return Check("bus state", status, f"{dev}: {state}{counters}", fix)


def _error_history(link: CanLink) -> Check:
    dev = link.name
    stats = link.controller_stats
    rx_err = link.rx_stats.get("errors", 0)
    tx_drop = link.tx_stats.get("dropped", 0)
    bad = {k: v for k, v in stats.items() if v and k in ("bus-errors", "bus-off", "error-pass", "re-started")}
    if not stats and not link.rx_stats:
        return Check("error history", Status.SKIP, f"{dev}: no statistics in the output (use -statistics)")
    parts = [f"{k} {v}" for k, v in bad.items()]
    if rx_err:
        parts.append(f"RX errors {rx_err}")
    if tx_drop:
        parts.append(f"TX dropped {tx_drop}")
    if not parts:
        return Check(
            "error history", Status.PASS, f"{dev}: no bus errors, bus-offs or drops since it came up"
        )
    return Check(
        "error history",
        Status.WARN,
        f"{dev}: " + ", ".join(parts) + " since it came up",
        "find the cause (termination, bitrate, a node in error); "
        "the counters reset when the interface is re-created",
    )
