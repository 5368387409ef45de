"""The conformance kit (``python -m firmware_sim.conformance``) against the simulated drive.

The reference drive and every variant PROTOCOL.md permits (sequence restart on enable, FAULT on a
COMMAND while DISABLED, frames padded to 8 bytes) pass every rule; the two deliberate violations
fail exactly the rules they break. The drive runs on its real-time clock; the kit counts time in
the drive's periods, and a loaded machine stretches the run instead of failing it: the watchdog is
wide (500 periods of 1 ms), so the kit's answering thread may stall for half a second beside the
drive's threads in this process.
"""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import can
import pytest
from fs_support import make_config, toml_text

from dob_hil.link.protocol import PROTOCOL_VERSION, DriveState, FrameKind, HeartbeatFrame
from firmware_sim import SimulatedDrive
from firmware_sim.behaviour import VARIANTS
from firmware_sim.conformance import RULES, KitOptions, run_conformance
from firmware_sim.conformance.__main__ import main as kit_main
from firmware_sim.conformance.probe import Rx
from firmware_sim.conformance.rules import _Book, _Session
from firmware_sim.process import standalone_drive

WATCHDOG_PERIODS = 500
DRIVE = {"watchdog_periods": WATCHDOG_PERIODS}
PLANT = {"period_us": 1000.0}
REPO = Path(__file__).resolve().parents[2]

# variant -> the rules it must fail (every other rule passes, none is skipped unless noted)
EXPECTED_FAILURES: dict[str, set[str]] = {
    "reference": set(),
    "restart-sequence": set(),
    "fault-on-command-while-disabled": set(),
    "padded": set(),
    "version-1": {"V1", "E1", "X2"},  # refuses our version: never enables, never clears
    "stale-stop-ignored": {"C2"},
}


@contextmanager
def fast_thread_switching() -> Iterator[None]:
    """The kit and the embedded drive share one GIL: hand it over every 100 us, not every 5 ms."""
    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-4)
    try:
        yield
    finally:
        sys.setswitchinterval(old)


@pytest.mark.parametrize("variant", sorted(EXPECTED_FAILURES))
def test_kit_against_the_drive_and_its_variants(
    variant: str, bus_pair: tuple[can.BusABC, can.BusABC]
) -> None:
    host_bus, drive_bus = bus_pair
    config = make_config(plant=PLANT, drive=DRIVE)
    options = KitOptions(
        node_id=1, watchdog_periods=WATCHDOG_PERIODS, full_current=True, answer_timeout_s=5.0
    )
    with (
        fast_thread_switching(),
        SimulatedDrive(drive_bus, config, clock="realtime", behaviour=VARIANTS[variant]) as drive,
    ):
        results = run_conformance(host_bus, options)
        final_state = drive.state
    by_status = {r.rule: r.status for r in results}
    assert [r.rule for r in results] == list(RULES)  # every rule, in the spec's order
    failed = {rule for rule, status in by_status.items() if status == "fail"}
    details = {r.rule: r.detail for r in results if r.status == "fail"}
    assert failed == EXPECTED_FAILURES[variant], details
    if not failed:
        assert set(by_status.values()) == {"pass"}
        assert final_state.name == "DISABLED"  # the kit leaves the drive as a host would


def test_kit_skips_full_current_rules_unless_asked(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, drive_bus = bus_pair
    config = make_config(plant=PLANT, drive=DRIVE)
    with fast_thread_switching(), SimulatedDrive(drive_bus, config, clock="realtime"):
        results = run_conformance(
            host_bus, KitOptions(watchdog_periods=WATCHDOG_PERIODS, answer_timeout_s=5.0)
        )
    skipped = {r.rule for r in results if r.status == "skip"}
    assert skipped == {"C1", "C2", "W4"}  # W4 needs full current with a watchdog this wide
    assert all(r.status == "pass" for r in results if r.rule not in skipped)


def test_kit_refuses_bad_arguments(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        kit_main(["--node", "16", "-i", "virtual", "-c", "x"])
    assert info.value.code == 2
    assert "--node must be 0..15, got 16" in capsys.readouterr().err
    assert kit_main(["-i", "no-such-interface", "-c", "x"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "no-such-interface" in err


@pytest.mark.realtime
def test_kit_command_against_a_standalone_drive(tmp_path: Path) -> None:
    """``python -m firmware_sim.conformance`` against ``python -m firmware_sim`` in another process,
    over udp_multicast on a private port (CAN_CONFIG), JSON out, exit 0."""
    port = random.randint(44000, 44999)
    env = {**os.environ, "CAN_CONFIG": json.dumps({"port": port})}
    channel = f"239.74.163.{random.randint(10, 250)}"
    node = random.randint(2, 15)
    cfg = tmp_path / "drive.toml"
    cfg.write_text(toml_text(plant=PLANT, drive={**DRIVE, "node_id": node}))
    try:
        drive_ctx = standalone_drive(cfg, "udp_multicast", channel, env=env)
        proc = drive_ctx.__enter__()
    except RuntimeError as exc:
        pytest.skip(f"udp_multicast unavailable: {exc}")
    try:
        out = subprocess.run(
            [sys.executable, "-m", "firmware_sim.conformance", "-i", "udp_multicast", "-c", channel,
             "--node", str(node), "--watchdog-periods", str(WATCHDOG_PERIODS), "--full-current",
             "--answer-timeout-ms", "5000", "--json"],
            check=False, env=env, cwd=REPO, capture_output=True, text=True, timeout=300,
        )  # fmt: skip
    finally:
        drive_ctx.__exit__(None, None, None)
    assert out.returncode == 0, out.stdout + out.stderr
    report = json.loads(out.stdout)
    assert report["protocol_version"] == PROTOCOL_VERSION and report["node_id"] == node
    assert {r["rule"]: r["status"] for r in report["results"]} == dict.fromkeys(RULES, "pass")
    assert proc.exit_status == 0, proc.stderr_text


def _heartbeats(*t_ms: int) -> list[Rx]:
    frame = HeartbeatFrame(state=DriveState.DISABLED, version=PROTOCOL_VERSION)
    return [
        Rx(index=i, t_ns=t * 1_000_000, kind=FrameKind.HEARTBEAT, data=b"", frame=frame)
        for i, t in enumerate(t_ms)
    ]


@pytest.mark.parametrize(
    ("windows", "passed", "observed"),
    [
        ([[0, 100, 200]], True, 1),
        ([[0, 350, 450], [0, 100, 200]], True, 2),  # one stall of the observer is forgiven
        ([[0, 350, 450]] * 3, False, 3),  # a gap in every window is the drive's
        ([[0]], False, 1),  # silent for a whole step: no second window
    ],
)
def test_h1_forgives_one_stalled_window_but_not_a_slow_drive(
    windows: list[list[int]], passed: bool, observed: int
) -> None:
    session = _Session.__new__(_Session)
    session.o = KitOptions()
    session.book = _Book()
    calls = iter(windows)
    seen: list[int] = []

    def window() -> tuple[list[Rx], list[Rx]]:
        seen.append(1)
        return _heartbeats(*next(calls)), []

    session._listen_window = window  # type: ignore[method-assign]
    session.listen()
    assert (session.book.results["H1"].status == "pass") is passed
    assert len(seen) == observed
