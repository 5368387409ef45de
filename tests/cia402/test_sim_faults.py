"""Watchdogs (SYNC loss, RPDO timeout), EMCY frames, fault reset, injected faults."""

from __future__ import annotations

import canopen
from sim_support import NODE, make_config, master_rig, raw_rig, sdo_request

from dob_hil.link.protocol import DriveState
from firmware_sim.cia402.power import PowerState

EMCY, RPDO1, TPDO1 = 0x80 + NODE, 0x200 + NODE, 0x180 + NODE
WATCHDOG = 10  # drive.watchdog_periods of the scenario


def _emcys(frames: list) -> list[str]:  # type: ignore[type-arg]
    return [bytes(m.data).hex() for m in frames if m.arbitration_id == EMCY]


def _running(rig, torque: int = 200, periods: int = 3) -> None:  # type: ignore[no-untyped-def]
    rig.enable()
    for _ in range(periods):
        rig.exchange(RPDO1, b"\x0f\x00" + torque.to_bytes(2, "little", signed=True))
        rig.sync()
    assert rig.drive.state is PowerState.OPERATION_ENABLED and rig.truths[-1].applied_current_A > 0


def test_sync_loss_faults_to_zero_current_with_emcy_8100() -> None:
    with raw_rig() as rig:
        _running(rig)
        frames = []
        for _ in range(WATCHDOG - 1):
            rig.drive.advance_period()
            frames += rig.drain()
        assert rig.drive.state is PowerState.OPERATION_ENABLED and _emcys(frames) == []
        rig.drive.advance_period()  # the watchdog_periods-th period without a SYNC
        assert _emcys(rig.drain()) == ["0081110000000000"]  # 0x8100, register generic|communication
        assert rig.drive.state is PowerState.FAULT and rig.drive.error_code == 0x8100
        rig.drive.advance_period()
        assert rig.truths[-1].applied_current_A == 0.0 and rig.truths[-1].drive_state is DriveState.FAULT
        statusword = int.from_bytes(rig.sdo(sdo_request(0x40, 0x6041, 0))[4:6], "little")
        assert statusword == 0x0208  # FAULT, remote
        assert rig.sdo(sdo_request(0x40, 0x603F, 0))[4:6] == b"\x00\x81"
        assert rig.sdo(sdo_request(0x40, 0x1001, 0))[4] == 0x11
        assert rig.sdo(sdo_request(0x40, 0x1003, 1))[4:8] == (0x8100).to_bytes(4, "little")


def test_rpdo_timeout_faults_with_emcy_8250_and_fault_reset_clears_it() -> None:
    with raw_rig() as rig:
        _running(rig)
        frames = []
        for _ in range(WATCHDOG):  # SYNCs keep coming, the RPDOs stop
            frames += rig.sync()
        assert _emcys(frames) == ["5082110000000000"]
        assert rig.drive.state is PowerState.FAULT
        tpdo = [bytes(m.data) for m in frames if m.arbitration_id == TPDO1]
        assert int.from_bytes(tpdo[-1][:2], "little") & 0x4F == 0x08  # the last TPDO says FAULT
        rig.exchange(RPDO1, b"\x0f\x00\x00\x00")
        rig.sync()
        assert rig.drive.state is PowerState.FAULT  # enabling does not clear a fault
        rig.exchange(RPDO1, b"\x80\x00\x00\x00")  # fault reset: rising edge of bit 7
        frames = rig.sync()
        assert _emcys(frames) == ["0000000000000000"]  # error reset
        assert rig.drive.state is PowerState.SWITCH_ON_DISABLED and rig.drive.error_code == 0
        assert rig.sdo(sdo_request(0x40, 0x1003, 0))[4] == 1  # the history keeps it
        assert rig.write(0x1003, 0, 0, 1)[0] == 0x60
        assert rig.sdo(sdo_request(0x40, 0x1003, 0))[4] == 0


def test_watchdogs_sleep_outside_operation_enabled() -> None:
    with raw_rig() as rig:
        rig.exchange(0x000, bytes([0x01, NODE]))
        for _ in range(3 * WATCHDOG):
            rig.sync()
            rig.drive.advance_period()
        assert rig.drive.state is PowerState.SWITCH_ON_DISABLED and _emcys(rig.drain()) == []


def test_leaving_operational_while_enabled_faults() -> None:
    with raw_rig() as rig:
        _running(rig)
        frames = rig.exchange(0x000, bytes([0x80, NODE]))
        assert _emcys(frames) == ["0081110000000000"]
        assert rig.drive.state is PowerState.FAULT


def _periods_with_faults(faults: dict[str, float], n: int) -> tuple[list[list], PowerState, int]:  # type: ignore[type-arg]
    """n SYNC periods with a torque RPDO each, under ``[sim.faults]``: frames per SYNC, end state, SYNCs."""
    with raw_rig(make_config(**{"sim.faults": faults})) as rig:
        rig.enable()
        per_sync = []
        for _ in range(n):
            rig.exchange(RPDO1, b"\x0f\x00\x64\x00")
            per_sync.append(rig.sync())
        return per_sync, rig.drive.state, rig.drive.stats.syncs


def test_injected_fault_and_silence_from_sim_faults() -> None:
    period_s = 300e-6
    per_sync, state, _ = _periods_with_faults({"fault_at_s": 5 * period_s}, 8)
    # 0x2310 over current, register generic|current
    assert _emcys([m for frames in per_sync for m in frames]) == ["1023030000000000"]
    assert state is PowerState.FAULT
    per_sync, _, syncs = _periods_with_faults({"silent_at_s": 4 * period_s}, 8)
    tpdos = [sum(m.arbitration_id == TPDO1 for m in frames) for frames in per_sync]
    assert tpdos == [1, 1, 1, 1, 0, 0, 0, 0] and syncs == 8  # silent, but it still listens


def test_canopen_emcy_consumer_decodes_the_sync_loss() -> None:
    with master_rig() as rig:
        node = rig.node
        node.sdo[0x6060].raw = 10
        node.nmt.state = "OPERATIONAL"
        for cw in (0x06, 0x07, 0x0F):
            node.sdo[0x6040].raw = cw
        node.network.sync.transmit()  # arms the watchdog
        rig.wait_for(lambda: rig.drive.stats.syncs == 1, "the SYNC")
        for _ in range(WATCHDOG):
            rig.drive.advance_period()
        rig.wait_for(lambda: bool(rig.emcys), "the EMCY")
        error = rig.emcys[-1]
        assert isinstance(error, canopen.emcy.EmcyError)
        assert (error.code, error.register) == (0x8100, 0x11)
        assert node.sdo[0x603F].raw == 0x8100
