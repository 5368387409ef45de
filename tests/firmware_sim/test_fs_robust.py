"""The simulated drive under hostile input and at its limits: stray datagrams and frames the bus
cannot deliver, a diverging plant, signals, and disturbances that start at enable (issue 10/11)."""

from __future__ import annotations

import dataclasses
import json
import os
import random
import signal
import socket
import time
from pathlib import Path

import can
import pytest
from fs_support import Host, make_config, toml_text

from dob_hil.link.protocol import (
    ControlRequest,
    DriveState,
    FaultCode,
    FaultFrame,
    FeedbackFrame,
    HeartbeatFrame,
    Status,
)
from firmware_sim import SimulatedDrive
from firmware_sim.process import standalone_drive

PLANT = {"period_us": 1000.0}
STEP = {"disturbance": [{"kind": "step", "amplitude_A": 0.2}]}


def test_realtime_drive_stays_at_rest_until_enabled(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    """Disturbances start at the first enable, so a real-time run starts from rest (as lockstep)."""
    host_bus, drive_bus = bus_pair
    host = Host(host_bus)
    config = make_config(plant=PLANT, sim=STEP, drive={"watchdog_periods": 1000})
    with SimulatedDrive(drive_bus, config, clock="realtime") as drive:
        host.wait_for(FeedbackFrame, timeout_s=10.0)
        while drive.period_index < 30:
            host.wait_for(FeedbackFrame, timeout_s=10.0)
        assert drive.true_state == (0.0, 0.0)  # 30 periods of a 0.2 A step: still at rest
        host.control(ControlRequest.ENABLE)
        host.wait_for(HeartbeatFrame, timeout_s=10.0)
        enabled_at = drive.period_index
        while drive.period_index < enabled_at + 30:
            host.wait_for(FeedbackFrame, timeout_s=10.0)
        assert drive.true_state[1] > 0.0  # the step acts from enable on
        assert drive.state is DriveState.ENABLED  # no command yet: the watchdog is not armed


def test_physics_overflow_is_an_encoder_fault_not_a_crash(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    host_bus, drive_bus = bus_pair
    base = make_config(sim={"disturbance": None})
    # beyond what the config parser may accept: built directly, as a diverging plant gets there
    config = dataclasses.replace(
        base,
        drive=dataclasses.replace(base.drive, encoder_counts_per_unit=1e300),
        sim=dataclasses.replace(base.sim, initial_state=(1e10, 0.0)),
    )
    host = Host(host_bus)
    drive = SimulatedDrive(drive_bus, config)
    host.control(ControlRequest.ENABLE)
    drive.service()
    assert drive.state is DriveState.FAULT
    drive.advance_period()  # and it keeps running: the FAULT frame, feedback with FAULT status
    frames = host.drain()
    assert FaultFrame(FaultCode.ENCODER, 0) in frames
    assert any(isinstance(f, FeedbackFrame) and f.status == Status.FAULT for f in frames)


def test_a_bad_datagram_does_not_stop_a_standalone_drive_and_sigint_does(tmp_path: Path) -> None:
    """A non-python-can datagram on the udp_multicast port is skipped; SIGINT stops the drive with
    exit status 0 and its summary (also with the spin-wait on)."""
    port = random.randint(45000, 45999)
    env = {**os.environ, "CAN_CONFIG": json.dumps({"port": port})}
    channel = f"239.74.163.{random.randint(10, 250)}"
    node = random.randint(2, 15)
    cfg = tmp_path / "drive.toml"
    cfg.write_text(toml_text(plant=PLANT, drive={"node_id": node, "watchdog_periods": 500}))
    try:
        can.Bus(interface="udp_multicast", channel=channel, port=port).shutdown()
    except (OSError, can.CanError) as exc:
        pytest.skip(f"udp_multicast unavailable: {exc}")
    bus: can.BusABC | None = None
    try:
        with standalone_drive(cfg, "udp_multicast", channel, env=env, spin_us=50) as proc:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
            for junk in (b"\xc1 not msgpack", b"\x81\xa3foo\x01"):  # invalid msgpack; not a frame
                sock.sendto(junk, (channel, port))
            sock.close()
            bus = can.Bus(interface="udp_multicast", channel=channel, port=port)  # after the junk
            host = Host(bus, node)
            host.control(ControlRequest.ENABLE)
            frames = host.wait_for(HeartbeatFrame, timeout_s=20.0)
            assert HeartbeatFrame(DriveState.ENABLED) in frames
            assert proc.alive()
            t0 = time.monotonic()
            proc.proc.send_signal(signal.SIGINT)
            proc.proc.wait(timeout=30)
            assert time.monotonic() - t0 < 30
    finally:
        if bus is not None:
            bus.shutdown()
    assert proc.exit_status == 0, proc.stderr_text
    assert "2 undeliverable frames" in proc.stderr_text, proc.stderr_text
