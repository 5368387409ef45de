"""The simulated CiA 402 drive on its real-time clock: in-process with a canopen master producing
SYNC, and ``python -m firmware_sim`` in its own process over udp_multicast (a private port)."""

from __future__ import annotations

import json
import os
import random
import time
from pathlib import Path

import can
import canopen
import pytest
from sim_support import TIMEOUT_S, make_config, unique_channel
from standalone import REPO_ROOT, node_id_for_worker, udp_channel_or_skip

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
    # patient watchdogs: 200 periods (SYNC every 1 ms here; a loaded machine stalls for milliseconds)
    config = make_config(drive={"watchdog_periods": 200})
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
    group = udp_channel_or_skip()
    port = random.randint(40000, 60000)  # a private port: no other test's frames (SYNC is broadcast)
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
