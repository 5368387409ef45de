"""NMT slave of the simulated drive: boot-up, state commands, resets, heartbeat producer on its clock."""

from __future__ import annotations

from sim_support import NODE, master_rig, raw_rig, sdo_request

HEARTBEAT = 0x700 + NODE


def _heartbeats(frames: list) -> list[bytes]:  # type: ignore[type-arg]
    return [bytes(m.data) for m in frames if m.arbitration_id == HEARTBEAT]


def test_boot_up_message_on_power_on_then_pre_operational() -> None:
    with raw_rig() as rig:
        assert [(m.arbitration_id, bytes(m.data)) for m in rig.boot_frames] == [(HEARTBEAT, b"\x00")]
        assert rig.drive.nmt_state == "PRE-OPERATIONAL"
        assert rig.drive.state.value == "SWITCH ON DISABLED"


def test_nmt_state_commands_addressed_and_broadcast() -> None:
    with raw_rig() as rig:
        for command, state in ((0x01, "OPERATIONAL"), (0x02, "STOPPED"), (0x80, "PRE-OPERATIONAL")):
            assert rig.exchange(0x000, bytes([command, NODE])) == []  # NMT is not confirmed
            assert rig.drive.nmt_state == state
        rig.exchange(0x000, bytes([0x01, 0]))  # node 0: all nodes
        assert rig.drive.nmt_state == "OPERATIONAL"
        rig.exchange(0x000, bytes([0x02, NODE + 1]))  # another node
        assert rig.drive.nmt_state == "OPERATIONAL"
        rig.exchange(0x000, bytes([0x02]))  # not an NMT frame (DLC 1)
        assert rig.drive.nmt_state == "OPERATIONAL"


def test_heartbeat_producer_runs_on_the_drive_clock() -> None:
    with raw_rig() as rig:
        assert rig.write(0x1017, 0, 3, 2)[0] == 0x60  # 3 ms
        rig.exchange(0x000, bytes([0x01, NODE]))
        frames = []
        for _ in range(31):  # lockstep: 31 SYNCs of 300 us span 9 ms of simulated time
            frames += rig.sync()
        assert _heartbeats(frames) == [b"\x05"] * 3
        rig.exchange(0x000, bytes([0x02, NODE]))  # STOPPED: heartbeat says 0x04
        frames = []
        for _ in range(10):
            frames += rig.sync()
        assert _heartbeats(frames) == [b"\x04"]
        rig.exchange(0x000, bytes([0x80, NODE]))
        assert rig.write(0x1017, 0, 0, 2)[0] == 0x60  # off
        frames = []
        for _ in range(40):
            frames += rig.sync()
        assert _heartbeats(frames) == []


def test_reset_node_restores_the_object_dictionary_and_boots_again() -> None:
    with raw_rig() as rig:
        rig.write(0x6072, 0, 1000, 2)
        rig.write(0x1017, 0, 5, 2)
        rig.enable()
        assert rig.drive.state.value == "OPERATION ENABLED"
        frames = rig.exchange(0x000, bytes([0x81, NODE]))
        assert [(m.arbitration_id, bytes(m.data)) for m in frames] == [(HEARTBEAT, b"\x00")]
        assert rig.drive.nmt_state == "PRE-OPERATIONAL"
        assert rig.drive.state.value == "SWITCH ON DISABLED"
        assert rig.sdo(sdo_request(0x40, 0x6072, 0))[4:6] == (2000).to_bytes(2, "little")
        assert rig.sdo(sdo_request(0x40, 0x1017, 0))[4:6] == b"\x00\x00"
        assert rig.sdo(sdo_request(0x40, 0x6060, 0))[4] == 0


def test_reset_communication_keeps_the_application_objects() -> None:
    with raw_rig() as rig:
        rig.write(0x6072, 0, 1000, 2)
        rig.write(0x1017, 0, 5, 2)
        frames = rig.exchange(0x000, bytes([0x82, NODE]))
        assert [(m.arbitration_id, bytes(m.data)) for m in frames] == [(HEARTBEAT, b"\x00")]
        assert rig.sdo(sdo_request(0x40, 0x6072, 0))[4:6] == (1000).to_bytes(2, "little")
        assert rig.sdo(sdo_request(0x40, 0x1017, 0))[4:6] == b"\x00\x00"


def test_canopen_nmt_master_sees_boot_up_and_heartbeats() -> None:
    with master_rig() as rig:
        rig.wait_for(lambda: 0 in rig.heartbeats, "the boot-up message")
        rig.node.nmt.state = "OPERATIONAL"
        rig.node.sdo[0x1017].raw = 2  # ms: with 300 us SYNCs, one heartbeat per 7 SYNCs
        rig.network.sync.start(0.001)
        assert rig.node.nmt.wait_for_heartbeat(10) == "OPERATIONAL"
        rig.node.nmt.state = "PRE-OPERATIONAL"
        rig.wait_for(lambda: rig.heartbeats[-1] == 0x7F, "a PRE-OPERATIONAL heartbeat")
