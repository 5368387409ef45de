"""The native profile's fault matrix (tests/faults/test_fault_matrix.py), mirrored for the CiA 402
profile in lockstep: paper-step-cia402 (1 s, 3333 samples) with transport faults from a seeded
FaultyBus on the host's end and drive faults from ``[sim.faults]``, each checked through its log.

For every case: no target torque beyond the limit (samples and raw RPDO frames), every injected
fault shows up as an event, and the run either completes and still tracks, or ends with a named
exit reason and the drive at zero current."""

from __future__ import annotations

import collections
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from dob_hil.config import Config, parse_config_text
from dob_hil.errors import DobHilError
from dob_hil.link.cia402 import codec
from dob_hil.link.protocol import DriveState
from dob_hil.log import LogData, read_log
from dob_hil.log.schemas import FLAG_FEEDBACK_MISSING
from dob_hil.loop.session import RunOptions, run_session
from dob_hil.scenarios import scenario_path
from firmware_sim.faulty_bus import FaultPlan, FaultyBus

NODE = 1
TPDO = codec.TPDO1_BASE + NODE
RPDO = codec.RPDO1_BASE + NODE
LIMIT_CODE = 1399
N_FAULT = 1000  # the period the timed faults happen at (0.3 s)


def _msg(aid: int, data: bytes = b"", **kw: Any) -> can.Message:
    return can.Message(arbitration_id=aid, data=data, is_extended_id=kw.pop("is_extended_id", False), **kw)


UNKNOWN_IDS = (
    _msg(0x7FF, b"\x01\x02\x03"),
    _msg(0x18FF50E5, bytes(8), is_extended_id=True),
    _msg(TPDO, is_remote_frame=True, dlc=6),  # a remote request on our TPDO id
)
OTHER_NODES = (  # plausible frames of other CiA 402 drives: they must never reach the controller
    _msg(TPDO + 1, codec.encode_tpdo1(0x0237, -777_777)),
    _msg(codec.EMCY_BASE + 3, codec.encode_emcy(codec.Emcy(0x2310, 0x03))),
    _msg(codec.HEARTBEAT_BASE + 5, b"\x05"),
    _msg(RPDO + 1, codec.encode_rpdo1(0x0F, 500)),
)
ERROR_FRAMES = (
    can.Message(is_error_frame=True, arbitration_id=0x20000004, data=bytes([0, 0x10, 0, 0, 0, 0, 0, 0])),
    can.Message(is_error_frame=True, arbitration_id=0x20000040, data=bytes(8)),  # bus off
)


@dataclass(frozen=True)
class Case:
    name: str
    plan: FaultPlan | None = None
    faults: dict[str, Any] = field(default_factory=dict)
    drive: dict[str, Any] = field(default_factory=dict)
    completes: bool | None = True  # None: either
    exit_match: str = "completed"
    events: tuple[str, ...] = ()  # event kinds that must appear
    equal_events: dict[str, tuple[str, ...]] = field(default_factory=dict)  # kind -> FaultyBus records
    rms_factor: float = 1.5  # completed runs: tracking RMS <= factor * the clean run's


CASES = [
    Case("clean"),
    Case("TPDO loss 1%", FaultPlan(seed=2, rx_match=TPDO, drop_probability=0.01), events=("feedback_lost",)),
    Case("TPDO loss 10%", FaultPlan(seed=3, rx_match=TPDO, drop_probability=0.10), events=("feedback_lost",),
         rms_factor=3.0),
    Case("duplicated TPDO 2%", FaultPlan(seed=4, rx_match=TPDO, duplicate_probability=0.02),
         equal_events={"stale_feedback": ("duplicate",)}),
    Case("reordered TPDO 2%", FaultPlan(seed=5, rx_match=TPDO, delay_probability=0.02),
         events=("stale_feedback", "feedback_lost")),
    Case("late TPDO 2% (2 Ts)", FaultPlan(seed=6, rx_match=TPDO, delay_probability=0.02, delay_frames=2),
         events=("stale_feedback", "feedback_lost")),
    Case("wrong DLC 2%", FaultPlan(seed=8, rx_match=TPDO, dlc_probability=0.02),
         equal_events={"malformed_frame": ("dlc",)}, events=("feedback_lost",)),
    Case("corrupted TPDO 0.5% (random bytes)", FaultPlan(seed=12, rx_match=TPDO, corrupt_probability=0.005),
         completes=None, exit_match=""),
    Case("unknown ids", FaultPlan(seed=9, rx_match=TPDO, inject_every=50, inject=UNKNOWN_IDS),
         equal_events={"foreign_frame": ("inject",)}),
    Case("other node ids", FaultPlan(seed=10, rx_match=TPDO, inject_every=7, inject=OTHER_NODES),
         equal_events={"foreign_frame": ("inject",)}),
    Case("error frames", FaultPlan(seed=11, rx_match=TPDO, inject_every=25, inject=ERROR_FRAMES),
         equal_events={"error_frame": ("inject_error",)}),
    Case("RPDO send raises once (buffer full)",
         FaultPlan(tx_match=RPDO, send_fail_at=N_FAULT, send_fail_count=1),
         completes=False, exit_match="Transmit buffer full", events=("send_failed",)),
    Case("sends raise from N on (bus off)",
         FaultPlan(tx_match=RPDO, send_fail_at=N_FAULT, send_fail_count=None, send_fail_message="Bus off"),
         completes=False, exit_match="Bus off", events=("send_failed",)),
    Case("every send lost from an RPDO at N on",
         FaultPlan(tx_match=RPDO, send_drop_at=N_FAULT, send_drop_count=None),
         completes=False, exit_match="host timeout|EMCY 0x8100|EMCY 0x8250"),
    Case("SYNCs lost from N on (SYNC loss)",
         FaultPlan(tx_match=codec.SYNC_ID, send_drop_at=N_FAULT, send_drop_count=None),
         completes=False, exit_match="host timeout|EMCY 0x8100"),
    Case("drive fault at N", faults={"fault_at_s": 0.3}, completes=False, exit_match="EMCY 0x2310",
         events=("drive_fault", "drive_state")),
    Case("drive silent from N", faults={"silent_at_s": 0.3}, completes=False, exit_match="host timeout"),
]  # fmt: skip


def _config(case: Case) -> Config:
    text = scenario_path("paper-step-cia402").read_text()
    for key, value in case.drive.items():
        text = re.sub(rf"(?m)^{key} = .*$", f"{key} = {value!r}", text)
    if case.faults:
        text += "\n[sim.faults]\n" + "".join(f"{k} = {v!r}\n" for k, v in case.faults.items())
    return parse_config_text(text)


@dataclass
class Outcome:
    error: DobHilError | None
    data: LogData
    bus: FaultyBus | None


def _run(case: Case, path: Path) -> Outcome:
    holder: dict[str, FaultyBus] = {}

    def wrap(bus: can.BusABC) -> can.BusABC:
        assert case.plan is not None
        holder["bus"] = FaultyBus(bus, case.plan)
        return holder["bus"]

    error: DobHilError | None = None
    try:
        run_session(_config(case), RunOptions(log_path=path, bus_wrapper=wrap if case.plan else None))
    except DobHilError as exc:
        error = exc
    return Outcome(error, read_log(path), holder.get("bus"))


def _rms(data: LogData, from_s: float = 0.1) -> float:
    s, t = data.samples, data.truth
    window = s["time_ns"] >= from_s * 1e9
    err = s["x_ref"][window, 0] - t["state"][: len(s), 0][window]
    return float(np.sqrt(np.mean(err**2)))


@pytest.fixture(scope="module")
def clean_rms(tmp_path_factory: pytest.TempPathFactory) -> float:
    return _rms(_run(CASES[0], tmp_path_factory.mktemp("clean") / "clean.mcap").data)


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_fault_case(case: Case, tmp_path: Path, clean_rms: float) -> None:
    out = _run(case, tmp_path / "case.mcap")
    data = out.data
    s, f = data.samples, data.frames
    reason = str(data.metadata["summary"]["exit_reason"])
    # safety: nothing beyond the limit, neither in the samples nor in any RPDO on the wire
    assert np.abs(s["dac_counts"]).max() <= LIMIT_CODE
    rpdo = f[(f["direction"] == 1) & (f["arbitration_id"] == RPDO)]
    torque = rpdo["data"][:, 2:4].copy().view("<i2")[:, 0]
    assert np.abs(torque).max() <= LIMIT_CODE
    # the drive ends at zero current: stopped by the host, or off by its own watchdog
    assert (
        data.truth["applied_current_a"][-1, 0] == 0.0 or data.truth["drive_state"][-1] != DriveState.ENABLED
    )
    if case.completes is True:
        assert out.error is None and reason == "completed", reason
        assert len(s) == 3333
        assert _rms(data) <= case.rms_factor * clean_rms
        missing = (s["flags"] & FLAG_FEEDBACK_MISSING) != 0
        if case.plan is not None and case.plan.drop_probability:
            assert missing.sum() == sum(1 for r in out.bus.record if r[0] == "drop")  # type: ignore[union-attr]
    elif case.completes is False:
        assert out.error is not None and re.search(case.exit_match, reason), reason
        assert len(s) < 3333
    kinds = collections.Counter(str(e["kind"]) for e in data.events)
    for kind in case.events:
        assert kinds[kind] > 0, (kind, kinds)
    for kind, records in case.equal_events.items():
        assert out.bus is not None
        injected = sum(1 for r in out.bus.record if r[0] in records)
        assert injected > 0 and kinds[kind] == injected, (kind, kinds[kind], injected)
