"""The simulated CiA 402 lockstep drive at a runaway position (its fused SYNC,
firmware_sim/cia402/fast.py, and its general path): an encoder fault (EMCY 0x7305, FAULT, torque
cut), never an exception out of the drive."""

from __future__ import annotations

from collections.abc import Iterator

import can
import pytest
from sim_support import NODE, make_config, sdo_request

from dob_hil.link.cia402 import codec
from dob_hil.loop.inproc_bus import bus_pair
from firmware_sim.cia402 import SimulatedCia402Drive
from firmware_sim.cia402.power import PowerState

SYNC = codec.SYNC_ID
RPDO = codec.RPDO1_BASE + NODE
SDO_RX = codec.SDO_RX_BASE + NODE


def _msg(aid: int, data: bytes = b"") -> can.Message:
    return can.Message(arbitration_id=aid, data=data, is_extended_id=False)


def _sdo_write(index: int, value: int, size: int, subindex: int = 0) -> can.Message:
    cs = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
    return _msg(SDO_RX, sdo_request(cs, index, subindex, value.to_bytes(size, "little", signed=value < 0)))


@pytest.fixture
def buses() -> Iterator[list[can.BusABC]]:
    made: list[can.BusABC] = []
    yield made
    for bus in made:
        bus.shutdown()


def _enabled(buses: list[can.BusABC], fast_path: bool) -> tuple[can.BusABC, SimulatedCia402Drive]:
    host, drive_end = bus_pair(f"review16-cia402-{len(buses)}")
    buses.extend((host, drive_end))
    drive = SimulatedCia402Drive(drive_end, make_config(), truth_sink=lambda t: None, fast_path=fast_path)

    def period(*frames: can.Message) -> None:
        for frame in frames:
            host.send(frame)
        drive.service()
        while host.recv(0.0) is not None:
            pass

    period()
    period(_sdo_write(0x1401, 0x80000301, 4, 1), _sdo_write(0x1801, 0x80000281, 4, 1))
    period(_sdo_write(0x6060, 10, 1), _msg(0, bytes((0x01, NODE))))  # CST, NMT start
    for cw in (0x06, 0x07, 0x0F):
        period(_sdo_write(0x6040, cw, 2))
    for _ in range(5):
        period(_msg(RPDO, codec.encode_rpdo1(0x0F, 100)), _msg(SYNC))
    assert drive.core.power.state is PowerState.OPERATION_ENABLED
    return host, drive


@pytest.mark.parametrize("fast_path", [True, False], ids=["fused", "general"])
def test_a_finite_position_beyond_the_encoder_range_is_an_encoder_fault(
    buses: list[can.BusABC], fast_path: bool
) -> None:
    """A runaway position that is finite but whose counts overflow (position * counts_per_unit =
    inf) is an encoder fault on both paths, as a non-finite position is: EMCY 0x7305, FAULT,
    torque cut. Before the fix Cia402Core._sample caught only ValueError and the fused SYNC called
    math.floor on the infinite product itself, so OverflowError escaped Cia402Lockstep.service
    and left the drive in OPERATION ENABLED with its torque applied."""
    host, drive = _enabled(buses, fast_path)
    drive.core.plant._x = [1.0e306, 0.0]
    host.send(_msg(RPDO, codec.encode_rpdo1(0x0F, 100)))
    host.send(_msg(SYNC))
    drive.service()  # raises OverflowError on main
    assert drive.core.power.state in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE)
    assert drive.core.error_code == 0x7305
    assert drive.core.path.final_A == 0.0
