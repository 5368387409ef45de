"""The CiA 402 power state machine: against canopen's own 402 tables, over SDO, and via BaseNode402."""

from __future__ import annotations

import pytest
from canopen.profiles.p402 import State402
from sim_support import NODE, master_rig, raw_rig, sdo_request

from firmware_sim.cia402.power import PowerState, PowerStateMachine

STATES = {s.value: s for s in PowerState}
AUTOMATIC = {("START", "NOT READY TO SWITCH ON"), ("NOT READY TO SWITCH ON", "SWITCH ON DISABLED"),
             ("FAULT REACTION ACTIVE", "FAULT")}  # fmt: skip


@pytest.mark.parametrize(
    ("transition", "controlword"),
    [(t, cw) for t, cw in State402.TRANSITIONTABLE.items() if t not in AUTOMATIC],
    ids=lambda v: "->".join(v) if isinstance(v, tuple) else f"{v:04X}",
)
def test_every_commanded_transition_of_canopens_table(transition: tuple[str, str], controlword: int) -> None:
    source, target = transition
    machine = PowerStateMachine()
    machine.boot()
    machine.state = STATES[source]
    machine.quick_stop_option = 6  # stays in QUICK STOP ACTIVE, so transition 16 exists
    assert machine.apply(controlword) is STATES[target]


@pytest.mark.parametrize("state", list(PowerState), ids=lambda s: s.value)
def test_statusword_patterns_match_canopens_masks(state: PowerState) -> None:
    machine = PowerStateMachine()
    machine.state = state
    sw = machine.statusword_bits
    matches = [name for name, (mask, value) in State402.SW_MASK.items() if sw & mask == value]
    assert matches == [state.value]


def test_fault_reset_needs_a_rising_edge_of_bit_7() -> None:
    machine = PowerStateMachine()
    machine.boot()
    machine.apply(0x80)  # bit 7 set while not in FAULT: nothing
    assert machine.state is PowerState.SWITCH_ON_DISABLED
    assert machine.fault() and machine.state is PowerState.FAULT_REACTION_ACTIVE
    machine.fault_reaction_done()
    assert machine.apply(0x80) is PowerState.FAULT  # bit 7 still set from before: no edge
    assert machine.apply(0x0F) is PowerState.FAULT  # enable refused in FAULT
    assert machine.apply(0x80) is PowerState.SWITCH_ON_DISABLED  # 0 -> 1: transition 15


def test_quick_stop_option_2_ends_in_switch_on_disabled_at_the_next_sync() -> None:
    machine = PowerStateMachine()
    machine.boot()
    for cw in (0x06, 0x07, 0x0F, 0x02):
        machine.apply(cw)
    assert machine.state is PowerState.QUICK_STOP_ACTIVE and not machine.torque_allowed
    assert machine.apply(0x0F) is PowerState.QUICK_STOP_ACTIVE  # no transition 16 with code 2
    machine.on_sync()
    assert machine.state is PowerState.SWITCH_ON_DISABLED


def test_statusword_over_sdo_through_enable_and_disable() -> None:
    with raw_rig() as rig:
        rig.write(0x6060, 0, 10, 1)
        seen = []
        for cw in (0x06, 0x07, 0x0F, 0x07, 0x06, 0x00):
            rig.write(0x6040, 0, cw, 2)
            seen.append(int.from_bytes(rig.sdo(sdo_request(0x40, 0x6041, 0))[4:6], "little"))
        # remote (bit 9) always; bit 12 "follows the command" in OPERATION ENABLED with mode 10
        assert seen == [0x0221, 0x0233, 0x1237, 0x0233, 0x0221, 0x0240]
        assert int.from_bytes(rig.sdo(sdo_request(0x40, 0x6061, 0))[4:5], "little") == 10


def test_canopen_basenode402_drives_the_state_machine_over_pdos() -> None:
    with master_rig() as rig:
        node = rig.node
        node.rpdo.read()
        node.rpdo[2].enabled = False  # its controlword would compete with RPDO1's (canopen drives RPDO1)
        node.rpdo.save()
        node.setup_402_state_machine()  # reads the drive's PDO maps: controlword in RPDO1, statusword TPDO1
        assert node.is_op_mode_supported("CYCLIC SYNCHRONOUS TORQUE")
        node.op_mode = "CYCLIC SYNCHRONOUS TORQUE"  # 0x6060 over SDO, checked through 0x6061
        assert node.op_mode == "CYCLIC SYNCHRONOUS TORQUE"
        node.nmt.state = "OPERATIONAL"
        node.rpdo[1].start(0.002)  # the master's cyclic RPDO and SYNC: the drive acts at each SYNC
        rig.network.sync.start(0.002)
        node.state = "OPERATION ENABLED"
        assert rig.drive.state is PowerState.OPERATION_ENABLED
        node.state = "SWITCHED ON"
        assert rig.drive.state is PowerState.SWITCHED_ON
        node.sdo[0x605A].raw = 6  # quick stop: stay in QUICK STOP ACTIVE
        node.state = "OPERATION ENABLED"
        node.state = "QUICK STOP ACTIVE"
        assert rig.drive.state is PowerState.QUICK_STOP_ACTIVE
        node.state = "SWITCH ON DISABLED"
        assert rig.drive.state is PowerState.SWITCH_ON_DISABLED
        assert node.nmt.state == "OPERATIONAL" and node.id == NODE
