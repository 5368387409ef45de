"""dob-hil doctor: the SocketCAN checks against recorded ip/ethtool output, and this host's checks."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from dob_hil.cli import main
from dob_hil.doctor import BusTarget, Status, run_doctor
from dob_hil.doctor.host import socketcan_support
from dob_hil.doctor.iplink import IpLinkParseError, parse_ip_link
from dob_hil.doctor.socketcan import check_link

FIXTURES = Path(__file__).parent / "fixtures"


def _text(name: str) -> str:
    return (FIXTURES / name).read_text()


def _by_name(checks: list) -> dict:  # type: ignore[type-arg]
    return {c.name: c for c in checks}


def test_parses_the_kernel_documentation_example() -> None:
    link = parse_ip_link(_text("sja1000_kerneldoc.txt"))
    assert (link.name, link.kind, link.up, link.txqueuelen) == ("can0", "can", True, 10)
    assert (link.can_state, link.restart_ms, link.bitrate_bps) == ("ERROR-ACTIVE", 100, 125000)
    assert link.controller_mode == ("TRIPLE-SAMPLING",)
    assert link.controller_stats == {
        "re-started": 41,
        "bus-errors": 17457,
        "arbit-lost": 0,
        "error-warn": 41,
        "error-pass": 42,
        "bus-off": 41,
    }
    assert link.rx_stats["errors"] == 17457
    assert link.tx_stats["dropped"] == 41


def test_parses_iproute2_6_with_counters_and_fd() -> None:
    healthy = parse_ip_link(_text("gs_usb_healthy.txt"))
    assert (healthy.tx_errors, healthy.rx_errors, healthy.bitrate_bps, healthy.txqueuelen) == (
        0,
        0,
        1_000_000,
        1000,
    )
    assert healthy.controller_stats["bus-off"] == 0
    assert healthy.rx_stats["packets"] == 667200
    fd = parse_ip_link(_text("peak_fd.txt"))
    assert fd.fd and fd.data_bitrate_bps == 5_000_000 and fd.bitrate_bps == 1_000_000
    vcan = parse_ip_link(_text("vcan0.txt"))
    assert vcan.kind == "vcan" and vcan.bitrate_bps is None and vcan.up


def test_healthy_interface_passes_every_check() -> None:
    checks = check_link(parse_ip_link(_text("gs_usb_healthy.txt")), bitrate_bps=1_000_000)
    assert {c.name: c.status for c in checks} == {
        "interface up": Status.PASS,
        "bitrate": Status.PASS,
        "txqueuelen": Status.PASS,
        "restart-ms": Status.PASS,
        "bus state": Status.PASS,
        "error history": Status.PASS,
    }


def test_bus_off_short_queue_no_restart_and_wrong_bitrate_are_reported_with_fixes() -> None:
    checks = _by_name(check_link(parse_ip_link(_text("gs_usb_busoff.txt")), bitrate_bps=1_000_000))
    assert checks["bus state"].status is Status.FAIL and "BUS-OFF" in checks["bus state"].detail
    assert "tx 248" in checks["bus state"].detail
    assert checks["bitrate"].status is Status.FAIL
    assert "500000" in checks["bitrate"].detail and "bitrate 1000000" in checks["bitrate"].fix
    assert checks["txqueuelen"].status is Status.WARN and "txqueuelen 1000" in checks["txqueuelen"].fix
    assert checks["restart-ms"].status is Status.WARN and "restart-ms 100" in checks["restart-ms"].fix
    history = checks["error history"]
    assert (
        history.status is Status.WARN and "bus-off 1" in history.detail and "TX dropped 17" in history.detail
    )


def test_down_interface_fails_with_the_command_to_bring_it_up() -> None:
    checks = _by_name(check_link(parse_ip_link(_text("gs_usb_down.txt")), bitrate_bps=None))
    assert checks["interface up"].status is Status.FAIL
    assert checks["interface up"].fix == "sudo ip link set can0 up"
    assert checks["bus state"].status is Status.FAIL  # STOPPED
    assert checks["bitrate"].status is Status.FAIL  # not configured


def test_can_fd_data_bitrate_is_checked() -> None:
    link = parse_ip_link(_text("peak_fd.txt"))
    ok = _by_name(check_link(link, bitrate_bps=1_000_000, data_bitrate_bps=5_000_000))
    assert ok["bitrate"].status is Status.PASS and "CAN FD" in ok["bitrate"].detail
    bad = _by_name(check_link(link, bitrate_bps=1_000_000, data_bitrate_bps=2_000_000))
    assert bad["bitrate"].status is Status.FAIL and "dbitrate 2000000" in bad["bitrate"].fix


def test_vcan_skips_controller_checks() -> None:
    checks = _by_name(check_link(parse_ip_link(_text("vcan0.txt")), bitrate_bps=1_000_000))
    assert checks["bitrate"].status is Status.SKIP
    assert checks["bus"].status is Status.WARN
    assert "bus state" not in checks


def test_hardware_timestamps_from_ethtool() -> None:
    target = BusTarget("socketcan", "can1", 1_000_000)
    hw = _by_name(run_doctor(target, ip_link_text=_text("peak_fd.txt"), ethtool_text=_text("ethtool_hw.txt")))
    assert hw["hardware timestamps"].status is Status.PASS
    sw = _by_name(run_doctor(target, ip_link_text=_text("peak_fd.txt"), ethtool_text=_text("ethtool_sw.txt")))
    assert sw["hardware timestamps"].status is Status.WARN


def test_garbage_ip_output_is_one_clear_error() -> None:
    with pytest.raises(IpLinkParseError):
        parse_ip_link('Device "can7" does not exist.\n')


def test_on_this_machine_socketcan_is_skipped_with_the_reason() -> None:
    support = socketcan_support()
    if support.status is Status.PASS:
        pytest.skip("this machine has SocketCAN: the skip path does not apply")
    checks = _by_name(run_doctor(BusTarget("socketcan", "can0", 1_000_000)))
    assert checks["SocketCAN"].status is Status.SKIP and "errno 97" in checks["SocketCAN"].detail
    assert "interface up" not in checks  # nothing checked against an interface that cannot exist
    assert {"SCHED_FIFO", "memory lock", "CPU governor", "isolated CPUs"} <= set(checks)


def test_udp_multicast_default_port_warns_private_port_passes() -> None:
    default = _by_name(run_doctor(BusTarget("udp_multicast", "239.74.163.2")))
    assert (
        default["udp_multicast port"].status is Status.WARN
        and "43113" in default["udp_multicast port"].detail
    )
    private = _by_name(run_doctor(BusTarget("udp_multicast", "239.74.163.2", port=50123)))
    assert private["udp_multicast port"].status is Status.PASS
    assert private["multicast route"].status in (Status.PASS, Status.WARN, Status.SKIP)
    bad = _by_name(run_doctor(BusTarget("udp_multicast", "10.0.0.1", port=50123)))
    assert bad["multicast group"].status is Status.FAIL


def test_cli_json_against_a_recorded_interface(capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["doctor", "paper-step", "-i", "socketcan", "-c", "can0", "--json",
               "--ip-link-file", str(FIXTURES / "gs_usb_busoff.txt")])  # fmt: skip
    report = json.loads(capsys.readouterr().out)
    assert rc == 1 and report["ok"] is False
    statuses = {c["name"]: c["status"] for c in report["checks"]}
    assert statuses["bus state"] == "fail" and statuses["bitrate"] == "fail"  # the config expects 1 Mbit/s
    assert report["target"]["bitrate_bps"] == 1_000_000


def test_cli_healthy_recording_exits_zero(capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["doctor", "-i", "socketcan", "-c", "can0", "-b", "1000000",
               "--ip-link-file", str(FIXTURES / "gs_usb_healthy.txt")])  # fmt: skip
    out = capsys.readouterr().out
    assert rc == 0 and "bus state" in out and "FAIL" not in out


def test_cli_missing_recording_is_one_line_exit_2(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    rc = main(["doctor", "-i", "socketcan", "--ip-link-file", str(tmp_path / "nope.txt")])
    err = capsys.readouterr().err
    assert rc == 2 and "--ip-link-file" in err and len(err.strip().splitlines()) == 1


def test_sched_fifo_check_leaves_the_policy_as_it_was() -> None:
    before = os.sched_getscheduler(0)
    run_doctor(BusTarget(None, None))
    assert os.sched_getscheduler(0) == before
