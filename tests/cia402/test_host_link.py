"""Cia402DriveLink against a CiA 402 slave built on canopen's LocalNode (tests/cia402/host_peer.py):
configuration over SDO, PDO mapping sequence, scaling checks, the power state machine (fault
reset, stuck states), the cyclic frames, stale / malformed / foreign frames, EMCY and safe stop."""

from __future__ import annotations

import itertools
import struct
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace

import can
import pytest
from host_peer import FAULT, OE, RTSO, SOD, PeerDrive

from dob_hil.config import Config, load_config
from dob_hil.errors import ConfigError, DriveFault
from dob_hil.link.base import LinkEvent, LinkEventKind
from dob_hil.link.cia402 import codec
from dob_hil.link.cia402.codec import PowerState
from dob_hil.link.cia402.link import Cia402DriveLink
from dob_hil.scenarios import scenario_path

_channels = itertools.count()
TIMEOUT_NS = 3_000_000_000
LIMIT_CODE = 1399  # floor(0.7 A / 0.0005 A) in exact arithmetic of the two doubles


@dataclass
class Rig:
    link: Cia402DriveLink
    peer: PeerDrive
    inject: can.BusABC
    frames: list[tuple[can.Message, bool]] = field(default_factory=list)
    events: list[LinkEvent] = field(default_factory=list)

    def kinds(self) -> list[LinkEventKind]:
        return [e.kind for e in self.events]

    def sdo_downloads(self) -> list[tuple[int, int, int]]:
        """(index, subindex, value) of every expedited SDO download the host sent, in order."""
        out = []
        for msg, is_rx in self.frames:
            if not is_rx and msg.arbitration_id == codec.SDO_RX_BASE + 1 and msg.data[0] & 0xE3 == 0x23:
                size = 4 - ((msg.data[0] >> 2) & 3)
                index, sub = struct.unpack_from("<HB", msg.data, 1)
                out.append((index, sub, int.from_bytes(msg.data[4 : 4 + size], "little")))
        return out


@pytest.fixture(scope="module")
def config() -> Config:
    return load_config(scenario_path("paper-step-cia402"))


@pytest.fixture
def make_rig(config: Config) -> Iterator[Callable[..., Rig]]:
    made: list[tuple[Rig, list[can.BusABC]]] = []

    def make(cfg: Config | None = None, **peer_kw: object) -> Rig:
        channel = f"cia402-host-{next(_channels)}"
        host, drive, inject = (can.Bus(interface="virtual", channel=channel) for _ in range(3))
        peer = PeerDrive(drive, **peer_kw)  # type: ignore[arg-type]
        frames: list[tuple[can.Message, bool]] = []
        events: list[LinkEvent] = []
        link = Cia402DriveLink(host, cfg or config, frame_hook=lambda m, rx: frames.append((m, rx)),
                               event_hook=events.append)  # fmt: skip
        rig = Rig(link, peer, inject, frames, events)
        made.append((rig, [host, drive, inject]))
        return rig

    yield make
    for rig, buses in made:
        rig.link.close()
        rig.peer.stop()
        for bus in buses:
            bus.shutdown()


def _wait(condition: Callable[[], bool], timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.001)


def test_enable_configures_the_drive_and_maps_the_pdos(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    rig.link.enable(TIMEOUT_NS)
    peer = rig.peer
    assert peer.mode == codec.MODE_CYCLIC_SYNC_TORQUE
    assert peer.statusword == OE and rig.link.power_state is PowerState.OPERATION_ENABLED
    assert peer.controlwords == [0x06, 0x07, 0x0F]  # shutdown, switch on, enable operation
    assert peer.nmt_commands == [codec.NmtCommand.ENTER_PRE_OPERATIONAL, codec.NmtCommand.START]
    assert [peer.stored(0x1600, s) for s in (0, 1, 2)] == [2, 0x60400010, 0x60710010]
    assert [peer.stored(0x1A00, s) for s in (0, 1, 2)] == [2, 0x60410010, 0x60640020]
    assert peer.stored(0x1400, 1) == 0x201 and peer.stored(0x1400, 2) == 1
    assert peer.stored(0x1800, 1) & 0x8000_07FF == 0x181 and peer.stored(0x1800, 2) == 1
    for unused in (0x1401, 0x1402, 0x1403, 0x1801, 0x1802, 0x1803):
        assert peer.stored(unused, 1) & 0x8000_0000, hex(unused)  # disabled
    assert peer.stored(0x1006) == 300  # communication cycle period in us
    assert peer.stored(0x1017) == 100  # heartbeat producer time in ms
    # the disable / map / enable sequence of CiA 301, in this order on the wire
    rpdo1 = [d for d in rig.sdo_downloads() if d[0] in (0x1400, 0x1600)]
    assert rpdo1 == [
        (0x1400, 1, 0x8000_0201),
        (0x1400, 2, 1),
        (0x1600, 0, 0),
        (0x1600, 1, 0x60400010),
        (0x1600, 2, 0x60710010),
        (0x1600, 0, 2),
        (0x1400, 1, 0x201),
    ]
    writes = rig.sdo_downloads()
    assert writes.index((0x6060, 0, 10)) < writes.index((0x1400, 1, 0x8000_0201))
    ident = rig.link.identity
    assert ident is not None and ident.rated_current_mA == 500 and ident.max_torque_permille == 2000
    assert any("CiA 402 device" in e.message for e in rig.events)


def test_cyclic_sync_tpdo_rpdo(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    link, peer = rig.link, rig.peer
    link.enable(TIMEOUT_NS)
    peer.position = 2**31 - 10
    link.send_trigger()
    fb = link.receive_feedback(TIMEOUT_NS)
    assert fb is not None and fb.seq == 0 and fb.enabled and not fb.fault and not fb.saturated
    assert fb.raw_counts == (2**31 - 10,) and fb.position == ((2**31 - 10) / 10000.0,)
    peer.position = -(2**31) + 5  # the i32 wraps: 15 increments further on
    link.send_trigger()
    fb = link.receive_feedback(TIMEOUT_NS)
    assert fb is not None and fb.seq == 1 and fb.counts == (2**31 + 5,)
    codes, applied, saturated = link.quantize((0.1,))
    assert codes == (200,) and applied == (200 * 0.0005,) and not saturated
    link.send_command(codes, fb.seq)
    link.send_command((LIMIT_CODE + 50,), fb.seq)  # clamped at the limit as the last step
    _wait(lambda: len(peer.rpdos) == 2)
    assert peer.rpdos == [(0x0F, 200), (0x0F, LIMIT_CODE)]
    assert link.stats.clamped_commands == 1
    tx = [m for m, rx in rig.frames if not rx and m.arbitration_id == codec.RPDO1_BASE + 1]
    assert [bytes(m.data) for m in tx] == [bytes.fromhex("0f00c800"), struct.pack("<Hh", 0x0F, LIMIT_CODE)]


def test_quantize_clamps_at_the_current_limit_through_the_rated_current(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    link = rig.link
    assert link.limit_code == LIMIT_CODE and LIMIT_CODE * 0.0005 <= 0.7
    assert link.quantize((0.7,)) == ((LIMIT_CODE,), (LIMIT_CODE * 0.0005,), True)
    assert link.quantize((-5.0,)) == ((-LIMIT_CODE,), (-LIMIT_CODE * 0.0005,), True)
    assert link.quantize((0.00074,)) == ((1,), (0.0005,), False)  # 1 per mille resolution
    assert link.quantize((float("nan"),)) == ((0,), (0.0,), True)
    assert rig.kinds() == [LinkEventKind.INVALID_COMMAND] and link.stats.nonfinite_currents == 1


def test_stale_malformed_foreign_and_emcy_frames(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    link = rig.link
    link.enable(TIMEOUT_NS)
    link.send_trigger()
    assert link.receive_feedback(TIMEOUT_NS) is not None
    send = rig.inject.send
    send(can.Message(arbitration_id=0x181, data=struct.pack("<Hi", OE, 7), is_extended_id=False))  # duplicate
    send(can.Message(arbitration_id=0x181, data=bytes(5), is_extended_id=False))  # wrong length
    send(can.Message(arbitration_id=0x182, data=struct.pack("<Hi", OE, 7), is_extended_id=False))  # node 2
    send(can.Message(arbitration_id=0x18FF50E5, data=bytes(8), is_extended_id=True))
    send(can.Message(is_error_frame=True, arbitration_id=0x20000040, data=bytes(8)))
    send(can.Message(arbitration_id=0x081, data=bytes.fromhex("5082110000000000"), is_extended_id=False))
    time.sleep(0.05)
    link.send_trigger()  # reads what is queued first
    fb = link.receive_feedback(TIMEOUT_NS)
    assert fb is not None and fb.seq == 1
    kinds = rig.kinds()
    for kind in (LinkEventKind.STALE_FEEDBACK, LinkEventKind.MALFORMED_FRAME, LinkEventKind.FOREIGN_FRAME,
                 LinkEventKind.ERROR_FRAME, LinkEventKind.DRIVE_FAULT):  # fmt: skip
        assert kind in kinds, kind
    fault = [e.message for e in rig.events if e.kind is LinkEventKind.DRIVE_FAULT]
    assert fault == ["node 1: EMCY 0x8250 (RPDO timeout), register 0x11"]
    assert "0x8250" in link.describe_fault()


def test_fault_in_the_tpdo_and_its_emcy(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    link, peer = rig.link, rig.peer
    link.enable(TIMEOUT_NS)
    peer.statusword = FAULT
    rig.inject.send(
        can.Message(arbitration_id=0x081, data=bytes.fromhex("1023030000000000"), is_extended_id=False)
    )
    link.send_trigger()
    fb = link.receive_feedback(TIMEOUT_NS)
    assert fb is not None and fb.fault and not fb.enabled
    text = link.describe_fault(1_000_000_000)
    assert "FAULT (statusword 0x0008)" in text and "EMCY 0x2310" in text


def test_missing_tpdo_is_counted_at_the_next_sync(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    link = rig.link
    link.enable(TIMEOUT_NS)
    rig.peer.nmt_commands.append(codec.NmtCommand.STOP)  # the peer stops answering SYNCs
    link.send_trigger()
    assert link.receive_feedback(50_000_000) is None
    link.send_trigger()
    assert link.stats.missed_feedback == 1


def test_safe_stop_zero_torque_then_disable_then_shutdown_each_with_a_sync(
    make_rig: Callable[..., Rig],
) -> None:
    rig = make_rig()
    link, peer = rig.link, rig.peer
    link.enable(TIMEOUT_NS)
    link.send_trigger()
    link.send_command((300,), 0)
    link.safe_stop()
    _wait(lambda: peer.nmt_commands[-1] == codec.NmtCommand.ENTER_PRE_OPERATIONAL)
    assert peer.rpdos == [(0x0F, 300), (0x0F, 0), (0x07, 0), (0x06, 0)]
    assert peer.statusword == RTSO
    tx = [(m.arbitration_id, bytes(m.data)) for m, rx in rig.frames if not rx][-7:]
    assert tx == [
        (0x201, bytes.fromhex("0f000000")), (0x080, b""),
        (0x201, bytes.fromhex("07000000")), (0x080, b""),
        (0x201, bytes.fromhex("06000000")), (0x080, b""),
        (0x000, b"\x80\x01"),
    ]  # fmt: skip
    n_tx = sum(1 for _, rx in rig.frames if not rx)
    link.safe_stop()  # repeatable: nothing more once stopped
    link.close()
    link.close()
    assert sum(1 for _, rx in rig.frames if not rx) == n_tx


def test_fault_at_enable_is_reset_with_a_rising_edge_of_bit_7(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig(statusword=FAULT)
    rig.link.enable(TIMEOUT_NS)
    assert rig.peer.controlwords == [0x00, 0x80, 0x06, 0x07, 0x0F]
    assert rig.peer.statusword == OE


@pytest.mark.parametrize(("statusword", "state"), [(SOD, "SWITCH_ON_DISABLED"), (FAULT, "FAULT")])
def test_a_stuck_drive_is_named_with_its_state_and_error_code(
    make_rig: Callable[..., Rig], statusword: int, state: str
) -> None:
    rig = make_rig(statusword=statusword, stuck=True, error_code=0x5530)
    with pytest.raises(DriveFault) as err:
        rig.link.enable(300_000_000)
    text = str(err.value)
    assert f"stuck in {state}" in text and "0x603F = 0x5530" in text and "0x6041" in text


@pytest.mark.parametrize(
    ("values", "field", "obj"),
    [
        ({(0x6075, 0): 1000}, "drive.dac_lsb_A", "0x6075"),
        ({(0x6072, 0): 1000}, "drive.current_limit_A", "0x6072"),
        ({(0x608F, 1): 4096}, "drive.encoder_counts_per_unit", "0x608F"),
        ({(0x1000, 0): 0x00020191}, "drive.profile", "0x1000"),
    ],
)
def test_a_config_the_drive_contradicts_is_refused_before_enabling(
    make_rig: Callable[..., Rig], values: dict[tuple[int, int], int], field: str, obj: str
) -> None:
    rig = make_rig(values=values)
    with pytest.raises(ConfigError) as err:
        rig.link.enable(TIMEOUT_NS)
    assert err.value.field == field and obj in str(err.value)
    assert rig.peer.controlwords == [] and rig.peer.mode == 0  # never enabled, never configured


def test_wrong_profile_or_node_id_is_refused(config: Config) -> None:
    bus = can.Bus(interface="virtual", channel="cia402-host-refuse")
    try:
        with pytest.raises(ConfigError, match=r"drive\.profile"):
            Cia402DriveLink(bus, replace(config, drive=replace(config.drive, profile="native")))
        with pytest.raises(ConfigError, match=r"drive\.node_id"):
            Cia402DriveLink(bus, replace(config, drive=replace(config.drive, node_id=0)))
    finally:
        bus.shutdown()
