"""The simulated CiA 402 drive on its real-time clock: in-process with a canopen master producing
SYNC, and ``python -m firmware_sim`` in its own process over udp_multicast (a private port)."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import can
import canopen
import pytest
from sim_support import TIMEOUT_S, make_config, unique_channel
from standalone import REPO_ROOT, node_id_for_worker
from udp_isolation import private_udp_channel

from dob_hil.scenarios import scenario_variant
from firmware_sim import process
from firmware_sim.cia402 import SimulatedCia402Drive
from firmware_sim.cia402.objects import shipped_eds
from firmware_sim.cia402.power import PowerState

pytestmark = pytest.mark.realtime


def _wait(condition, what: str) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + TIMEOUT_S
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.002)


def _master_node(network: canopen.Network, node_id: int) -> canopen.BaseNode402:
    node = canopen.BaseNode402(node_id, str(shipped_eds()))
    node.sdo.RESPONSE_TIMEOUT = TIMEOUT_S
    network.add_node(node)
    return node


def _enable_over_sdo(node: canopen.BaseNode402) -> None:
    node.sdo[0x6060].raw = 10
    node.nmt.state = "OPERATIONAL"
    for cw in (0x06, 0x07, 0x0F):
        node.sdo[0x6040].raw = cw


def test_realtime_drive_follows_the_masters_sync_and_faults_when_it_stops() -> None:
    # patient watchdogs: 1000 periods (SYNC every 1 ms here, from canopen's producer thread, which a
    # loaded machine has been seen to stall for more than 200 ms); the trip after the SYNC stops
    # then takes a second, well inside TIMEOUT_S
    config = make_config(drive={"watchdog_periods": 1000})
    channel = unique_channel()
    bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel, receive_own_messages=False)
    emcys: list[canopen.emcy.EmcyError] = []
    try:
        node = _master_node(network, 1)
        node.emcy.add_callback(emcys.append)
        with SimulatedCia402Drive(bus, config, clock="realtime") as drive:
            node.sdo[0x1006].raw = 1000  # us: the SYNC period below
            _enable_over_sdo(node)
            node.tpdo.read()
            node.rpdo.read()
            node.rpdo[1]["Controlword"].raw = 0x0F
            node.rpdo[1].start(0.001)  # keeps the RPDO-timeout watchdog fed
            network.sync.start(0.001)
            assert node.tpdo[1].wait_for_reception(TIMEOUT_S) is not None
            assert {v.index: v.raw for v in node.tpdo[1]}[0x6041] == 0x1237
            _wait(lambda: drive.period_index > 20, "20 SYNC periods")
            assert drive.state is PowerState.OPERATION_ENABLED, (hex(drive.error_code), drive.stats)
            network.sync.stop()  # the RPDOs go on: only the SYNC is lost
            _wait(lambda: bool(emcys), "the SYNC-loss EMCY")
            assert (emcys[0].code, emcys[0].register) == (0x8100, 0x11)
            assert drive.state is PowerState.FAULT
            drive.check()
    finally:
        network.disconnect()
        bus.shutdown()


def test_standalone_process_is_a_cia402_slave_over_udp_multicast(tmp_path: Path) -> None:
    with private_udp_channel() as chan:  # a private namespace and port (SYNC is broadcast)
        _run_standalone(tmp_path, chan.channel, chan.port)


def _run_standalone(tmp_path: Path, group: str, port: int) -> None:
    node_id = node_id_for_worker()
    # this master sends each SYNC after the previous TPDO arrived: tens of ms apart on a loaded
    # machine, so the SYNC-loss watchdog gets 20000 periods (6 s) here (its trip is tested above)
    config = scenario_variant("paper-step-cia402", tmp_path, node_id=node_id, patience_periods=20000)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env["CAN_CONFIG"] = json.dumps({"port": port})
    network = canopen.Network()
    network.connect(interface="udp_multicast", channel=group, port=port)
    heartbeats: list[int] = []
    try:
        node = _master_node(network, node_id)
        node.nmt.add_heartbeat_callback(heartbeats.append)
        with process.standalone_drive(config, "udp_multicast", group, env=env, ready_timeout_s=30.0) as drive:
            _wait(lambda: 0 in heartbeats, "the boot-up message")
            assert node.sdo[0x1000].raw == 0x00020192
            assert node.sdo[0x1008].raw.startswith("dob_hil generic CiA 402")  # segmented upload
            node.tpdo.read()
            _enable_over_sdo(node)
            node.rpdo.read()
            node.rpdo[1]["Controlword"].raw = 0x0F
            node.rpdo[1]["Target torque"].raw = 200
            received: list[dict[int, int]] = []  # decoded by canopen's map (no wait_for_reception race)
            node.tpdo[1].add_callback(lambda m: received.append({v.index: v.raw for v in m}))
            positions = []
            for k in range(20):
                node.rpdo[1].transmit()
                network.sync.transmit()
                _wait(lambda k=k: len(received) > k, "the TPDO of the SYNC")
                values = received[k]
                assert values[0x6041] & 0x6F == 0x27  # OPERATION ENABLED
                positions.append(values[0x6064])
            assert positions[-1] != positions[0]  # the plant moved under the torque
            node.sdo[0x6040].raw = 0x06
            assert node.sdo[0x6041].raw & 0x6F == 0x21  # READY TO SWITCH ON
            assert drive.alive
        assert drive.exit_status == 0, drive.stderr_text
    finally:
        network.disconnect()


def test_real_time_core_samples_at_the_sync_arrival_and_judges_loss_on_its_clock() -> None:
    """The real-time clock's firmware without the thread: frames handed over with their arrival."""
    from firmware_sim.cia402.core import Cia402Core

    config = make_config(drive={"watchdog_periods": 4}, sim={"disturbance": None})
    channel = unique_channel()
    host = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    try:
        core = Cia402Core(bus, config, lockstep=False, want_truth=True)
        core.power_on()
        for cw in (0x06, 0x07, 0x0F):
            core.on_frame(0x601, bytes([0x2B, 0x40, 0x60, 0, cw, 0, 0, 0]), 1_000)
        core.on_frame(0x601, bytes([0x2F, 0x60, 0x60, 0, 10, 0, 0, 0]), 1_000)
        core.on_frame(0x000, bytes([0x01, 1]), 1_000)
        indices = []
        for arrival_ns in (50_000, 360_000, 640_000, 1_560_000):  # jitter, then two SYNCs lost
            core.on_frame(0x201, bytes([0x0F, 0, 100, 0]), arrival_ns - 20_000)
            core.on_frame(0x80, b"", arrival_ns)
            assert core.time_ns == arrival_ns  # integrated to the arrival, not to k Ts
            indices.append(core.period_index)
            core.tick(arrival_ns)
        assert indices == [0, 1, 2, 5]  # the nominal 300 us grid from the first SYNC
        assert core.take_truth() is not None
        core.tick(1_560_000 + 3 * 300_000)  # three periods without SYNC: not yet
        assert core.power.state is PowerState.OPERATION_ENABLED
        core.tick(1_560_000 + 4 * 300_000 + 1)
        assert core.power.state is PowerState.FAULT and core.error_code == 0x8100
        assert core.time_ns == 1_560_000 + 4 * 300_000  # the current was cut at the deadline
        core.on_frame(0x80, b"", 3_000_000)
        truth = core.take_truth()
        assert truth is not None and truth.applied_current_A == 0.0 and truth.time_ns == 3_000_000
    finally:
        host.shutdown()
        bus.shutdown()
