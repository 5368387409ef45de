"""The lockstep drive's fused period (firmware_sim.cia402.fast) against its general path.

The general path (every frame through ``Cia402Core.on_frame``) is the specification. Each case runs
twice, once as shipped and once with the fused period switched off, and the two must give exactly
the same records: every sample (but its compute time), frame, truth record and event of a whole
lockstep session, or every frame the drive sends, its truth and its state when the drive is
driven frame by frame. The cases put everything the fused period must hand back to the general
path in the middle of a run: injected faults, TPDO loss, encoder noise, SDO reads and writes, NMT
commands, controlword changes (disable, halt, fault reset bit, quick stop), RPDOs of the wrong
length or missing, a SYNC of the wrong length or lost, other frames, an encoder fault, the SYNC
counter, the velocity TPDO, a longer input delay and a faster heartbeat.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import pytest
from plants import PLANT_3
from sim_support import NODE, make_config, sdo_request

from dob_hil.config import Config
from dob_hil.errors import DobHilError
from dob_hil.link.cia402 import codec
from dob_hil.log.digest import log_digest
from dob_hil.loop.inproc_bus import bus_pair
from dob_hil.loop.session import RunOptions, run_session
from firmware_sim.cia402 import SimulatedCia402Drive
from firmware_sim.cia402 import lockstep as lockstep_module
from firmware_sim.cia402.fast import FastPeriod
from firmware_sim.faulty_bus import FaultPlan, FaultyBus
from firmware_sim.truth import GroundTruth

SYNC = codec.SYNC_ID
RPDO = codec.RPDO1_BASE + NODE
SDO_RX = codec.SDO_RX_BASE + NODE
DURATION_S = 0.15  # 500 samples
N_SAMPLES = 500


def _msg(aid: int, data: bytes = b"") -> can.Message:
    return can.Message(arbitration_id=aid, data=data, is_extended_id=False)


def _rpdo(controlword: int, torque: int = 0) -> can.Message:
    return _msg(RPDO, codec.encode_rpdo1(controlword, torque))


def _sdo_write(index: int, value: int, size: int, subindex: int = 0) -> can.Message:
    cs = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
    return _msg(SDO_RX, sdo_request(cs, index, subindex, value.to_bytes(size, "little", signed=value < 0)))


class Injector(can.BusABC):
    """The host's end of the bus, sending extra frames just before the n-th SYNC (after that
    period's RPDO from the host): ``schedule[n]``."""

    def __init__(self, inner: can.BusABC, schedule: dict[int, tuple[can.Message, ...]]) -> None:
        self.inner = inner
        self.schedule = schedule
        self.syncs = 0
        super().__init__(channel="injector")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if msg.arbitration_id == SYNC and not msg.is_extended_id:
            for extra in self.schedule.get(self.syncs, ()):
                self.inner.send(_msg(extra.arbitration_id, bytes(extra.data)))
            self.syncs += 1
        self.inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.inner.recv(timeout), False

    def shutdown(self) -> None:
        self.inner.shutdown()
        super().shutdown()


@dataclass
class Counter:
    fast: int = 0


@pytest.fixture
def fast_syncs(monkeypatch: pytest.MonkeyPatch) -> Counter:
    """Counts the SYNCs the fused period took."""
    counter = Counter()
    sync = FastPeriod.sync

    def counting(self: FastPeriod, *args: Any) -> bool:
        taken = sync(self, *args)
        counter.fast += taken
        return taken

    monkeypatch.setattr(FastPeriod, "sync", counting)
    return counter


@pytest.fixture
def general_path(monkeypatch: pytest.MonkeyPatch) -> Callable[[], None]:
    """``general_path()``: no fused period from now on (the plan never applies)."""

    def switch() -> None:
        monkeypatch.setattr(lockstep_module, "fast_plan", lambda core: None)

    return switch


# --- whole sessions ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Case:
    name: str
    sections: dict[str, dict[str, Any]] = field(default_factory=dict)
    schedule: dict[int, tuple[can.Message, ...]] = field(default_factory=dict)
    plan: FaultPlan | None = None
    sim_delay: int | None = None  # the simulated drive's plant.input_delay_samples (the host's: 1)
    fast_at_least: float = 0.0  # the share of samples the fused period must have taken


CASES = [
    Case("clean", fast_at_least=0.95),
    Case("noise and TPDO loss", {"sim": {"noise_counts_std": 2.0, "loss_probability": 0.05, "seed": 7}},
         fast_at_least=0.85),
    Case("SYNC counter, 10 ms heartbeat", {"drive.cia402": {"sync_counter": True, "heartbeat_ms": 10}},
         fast_at_least=0.95),
    Case("injected faults: encoder jump, then a drive fault",
         {"sim.faults": {"encoder_jump_at_s": 0.05, "encoder_jump_counts": 3, "fault_at_s": 0.1}}),
    Case("drive silent", {"sim.faults": {"silent_at_s": 0.1}}),
    Case("SDO, controlword and odd frames mid-run", schedule={
        60: (_sdo_write(0x6071, 100, 2),),  # target torque by SDO: overrides the RPDO's at the SYNC
        80: (_msg(SDO_RX, sdo_request(0x40, 0x6041, 0)),),  # SDO read of the statusword
        100: (_rpdo(0x07),),  # disable operation; the host's next RPDO enables again
        130: (_rpdo(0x10F, 50),),  # halt
        150: (_rpdo(0x8F, 20),),  # the fault reset bit while enabled: no command
        200: (_msg(RPDO, b"\x0f\x00\x10"),),  # too short: not processed (EMCY 0x8210)
        210: (_msg(RPDO, codec.encode_rpdo1(0x0F, 30) + b"\x00\x00"),),  # too long: processed (0x8220)
        220: (_rpdo(0x0F, -40), _rpdo(0x0F, 40)),  # three RPDOs in one period
        230: (_msg(0x7FF, b"\x01"),),  # no frame of this drive
        240: (_sdo_write(0x1017, 5, 2),),  # heartbeat every 5 ms from now
        260: (_sdo_write(0x6072, 200, 2),),  # max torque down: clamped, statusword bit 11
        300: (_sdo_write(0x6072, 1500, 2),),
    }, fast_at_least=0.8),
    Case("quick stop", schedule={150: (_rpdo(0x0B),)}),
    Case("NMT pre-operational while enabled", schedule={150: (_msg(0, bytes((0x80, NODE))),)}),
    Case("SYNC of the wrong length", schedule={150: (_msg(SYNC, b"\x01\x02"),)}),
    Case("RPDOs lost (watchdog counts)",
         plan=FaultPlan(tx_match=RPDO, send_drop_at=100, send_drop_count=2)),
    Case("a SYNC lost", plan=FaultPlan(tx_match=SYNC, send_drop_at=100, send_drop_count=1)),
    Case("the drive's input delay one period longer", sim_delay=2, fast_at_least=0.95),
]  # fmt: skip


def _session(case: Case, config: Config, path: Path) -> tuple[str, str]:
    def wrap(bus: can.BusABC) -> can.BusABC:
        if case.plan is not None:
            bus = FaultyBus(bus, case.plan)
        return Injector(bus, case.schedule) if case.schedule else bus

    sim_config = None
    if case.sim_delay is not None:
        plant = dataclasses.replace(config.plant, input_delay_samples=case.sim_delay)
        sim_config = dataclasses.replace(config, plant=plant)
    options = RunOptions(duration_s=DURATION_S, log_path=path, bus_wrapper=wrap, sim_config=sim_config)
    try:
        summary = run_session(config, options)
        outcome = summary.exit_reason
    except DobHilError as exc:
        outcome = f"{type(exc).__name__}: {exc}"
    return outcome, repr(log_digest(path))  # the counts and the full sha256


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_a_session_logs_the_same_records_with_and_without_the_fused_period(
    case: Case, tmp_path: Path, fast_syncs: Counter, general_path: Callable[[], None]
) -> None:
    config = make_config(**case.sections)
    fast = _session(case, config, tmp_path / "fast.mcap")
    taken = fast_syncs.fast
    general_path()
    general = _session(case, config, tmp_path / "general.mcap")
    assert fast_syncs.fast == taken  # the general run never took the fused period
    assert fast == general
    assert taken >= case.fast_at_least * N_SAMPLES, taken


# --- frame by frame -----------------------------------------------------------------------------------
@dataclass
class Rig:
    """The drive on an in-process bus, fed raw frames; everything it sends, and its state after each
    service, is kept in order."""

    host: can.BusABC
    drive: SimulatedCia402Drive
    truths: list[GroundTruth]
    sent: list[tuple[int, bytes]] = field(default_factory=list)
    trace: list[tuple[Any, ...]] = field(default_factory=list)

    def period(self, *frames: can.Message) -> None:
        for frame in frames:
            self.host.send(_msg(frame.arbitration_id, bytes(frame.data)))
        self.drive.service()
        while (msg := self.host.recv(0.0)) is not None:
            self.sent.append((msg.arbitration_id, bytes(msg.data)))
        self.trace.append(self.state())

    def state(self) -> tuple[Any, ...]:
        """Everything the drive's behaviour depends on (firmware internals included)."""
        core = self.drive.core
        return (
            core.time_ns, core.period_index, core.counts, core.velocity, core.saturated, core.target_torque,
            core.mode, core.power.state, core.power.controlword, core.error_code, tuple(core.error_history),
            core.plant.state, core.path.held_A, core.path.pending, core.path.final_A,
            dataclasses.replace(core.stats), core.node.nmt.state, core._missed_rpdo, core._missed_sync,
            core._watch_armed, core._rpdo_since_sync, core._last_sync_ns, core._sample_t_ns,
            dict(core._pending), tuple(core._tpdo_syncs), tuple(core._tpdo_last), core._next_heartbeat_ns,
        )  # fmt: skip


@pytest.fixture
def rig_of() -> Iterator[Callable[..., Rig]]:
    buses: list[can.BusABC] = []

    def make(fast_path: bool, config: Config | None = None) -> Rig:
        host, drive_end = bus_pair(f"fast-path-{len(buses)}")
        buses.extend((host, drive_end))
        truths: list[GroundTruth] = []
        config = make_config() if config is None else config
        drive = SimulatedCia402Drive(drive_end, config, truth_sink=truths.append, fast_path=fast_path)
        rig = Rig(host, drive, truths)
        rig.period()  # the boot-up frame
        # the host link's PDOs (the EDS's defaults have a second RPDO and TPDO): those two off
        rig.period(_sdo_write(0x1401, 0x80000301, 4, 1), _sdo_write(0x1801, 0x80000281, 4, 1))
        rig.period(_sdo_write(0x6060, 10, 1), _msg(0, bytes((0x01, NODE))))  # CST, NMT start
        for cw in (0x06, 0x07, 0x0F):
            rig.period(_sdo_write(0x6040, cw, 2))
        return rig

    yield make
    for bus in buses:
        bus.shutdown()


def _script(rig: Rig) -> None:
    for k in range(40):
        rig.period(_rpdo(0x0F, 10 * k - 200), _msg(SYNC))
    read_velocity = _msg(SDO_RX, sdo_request(0x40, 0x606C, 0))
    rig.period(_rpdo(0x0F, 30), read_velocity, _msg(SDO_RX, sdo_request(0x40, 0x6064, 0)), _msg(SYNC))
    # the RPDO watchdog (10 periods): 6 missed, one RPDO (fused period), 6 missed: no fault
    for _ in range(2):
        for _ in range(6):
            rig.period(_msg(SYNC))
        rig.period(_rpdo(0x0F, 30), _msg(SYNC))
        rig.period(_rpdo(0x0F, 30), _msg(SYNC))
    rig.period(_rpdo(0x0F, 30))  # an RPDO held over a service without a SYNC
    rig.period(_msg(SYNC))
    rig.drive.advance_period()
    for _ in range(5):
        rig.period(_rpdo(0x0F, 50), _msg(SYNC))
    # TPDO1 every second SYNC from now (the count of SYNCs goes on from the fused periods')
    rig.period(_rpdo(0x0F, 50), _sdo_write(0x1800, 2, 1, 2), _msg(SYNC))
    for _ in range(3):
        rig.period(_rpdo(0x0F, 50), _msg(SYNC))
    rig.period(_rpdo(0x0F, 50), _sdo_write(0x1800, 1, 1, 2), _msg(SYNC))
    for _ in range(3):
        rig.period(_rpdo(0x0F, 50), _msg(SYNC))
    rig.period(read_velocity)
    rig.drive.core.plant._x = [math.nan, math.nan]  # the plant runs away: no finite position
    rig.period(_rpdo(0x0F, 50), _msg(SYNC))  # an encoder fault half-way through the fused period
    for cw in (0x00, 0x80, 0x06, 0x07, 0x0F):
        rig.period(_rpdo(cw, 0), _msg(SYNC))


def test_frame_by_frame_the_drive_sends_and_does_the_same_with_and_without_the_fused_period(
    rig_of: Callable[..., Rig], fast_syncs: Counter
) -> None:
    fast, general = rig_of(True), rig_of(False)
    _script(fast)
    taken = fast_syncs.fast
    _script(general)
    assert fast_syncs.fast == taken
    assert taken >= 40
    assert fast.sent == general.sent
    assert repr(fast.truths) == repr(general.truths)  # exact floats, the runaway's NaN state too
    assert len(fast.trace) == len(general.trace)
    for k, (a, b) in enumerate(zip(fast.trace, general.trace, strict=True)):
        assert repr(a) == repr(b), f"after service {k}"
    assert fast.drive.core.error_code == 0x7305  # the encoder fault happened, in both
    assert 0x8250 not in fast.drive.core.error_history  # no RPDO timeout
    assert any(aid == 0x080 + NODE for aid, _ in fast.sent)  # its EMCY


def test_a_position_that_cannot_be_computed_is_an_encoder_fault_on_both_paths(
    rig_of: Callable[..., Rig], fast_syncs: Counter
) -> None:
    """A 3-state plant's position() is math.fsum, which raises ValueError for +inf and -inf among
    its terms (a 2-state position gives NaN): an encoder fault on both paths."""
    config = make_config(plant=PLANT_3, **{"design.estimator": {"Lc": None}, "design.feedback": {"Kc": None}})
    rigs = []
    for fast_path in (True, False):
        rig = rig_of(fast_path, config)
        for k in range(10):
            rig.period(_rpdo(0x0F, 10 * k), _msg(SYNC))
        taken = fast_syncs.fast

        def unmeasurable() -> float:
            return math.fsum((math.inf, -math.inf))  # raises ValueError

        rig.drive.core.plant.position = unmeasurable  # type: ignore[method-assign]
        rig.period(_rpdo(0x0F, 50), _msg(SYNC))
        rig.period(_rpdo(0x00, 0), _msg(SYNC))
        assert rig.drive.core.error_code == 0x7305, fast_path  # the encoder fault, no exception
        assert any(aid == 0x080 + NODE for aid, _ in rig.sent)  # its EMCY
        rigs.append((rig, taken))
    (fast, fast_taken), (general, _) = rigs
    assert fast_taken >= 9  # the fused period ran before the fault
    assert fast.sent == general.sent
    assert repr(fast.truths) == repr(general.truths)
    assert [repr(a) for a in fast.trace] == [repr(b) for b in general.trace]


def test_the_fused_period_sends_the_tpdo_message_canopen_would(rig_of: Callable[..., Rig]) -> None:
    """The TPDO leaves as the same python-can Message as canopen's Network.send_message builds."""
    rig = rig_of(True)
    rig.period(_rpdo(0x0F, 10), _msg(SYNC))
    rig.host.send(_msg(RPDO, codec.encode_rpdo1(0x0F, 10)))
    rig.host.send(_msg(SYNC))
    rig.drive.service()
    msg = rig.host.recv(0.0)
    assert msg is not None and msg.arbitration_id == codec.TPDO1_BASE + NODE
    reference = can.Message(is_extended_id=False, arbitration_id=msg.arbitration_id, data=bytes(msg.data))
    slots = [s for s in can.Message.__slots__ if s != "__weakref__"]
    assert {s: getattr(msg, s) for s in slots} == {s: getattr(reference, s) for s in slots}
    assert isinstance(msg.data, bytearray) and msg.dlc == 6
