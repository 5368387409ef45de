"""The native profile's fault matrix (tests/faults) run against the ODrive profile, in lockstep:
paper-step-odrive (1 s, 1000 samples) with a seeded FaultyBus on the host's bus end or faults the
simulated ODrive injects. (Injection intervals do not divide 1000: a frame injected after the
last estimate would never be read.) For every case: the current never beyond the limit (samples and raw
Set_Input_Torque frames), every injected fault shows up as its event, the run either completes
and still tracks, or ends with a named reason; a drive-side trip is measured in periods."""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from dob_hil.errors import DobHilError
from dob_hil.link.odrive import codec
from dob_hil.link.odrive.codec import AxisState, CmdId, Heartbeat
from dob_hil.link.protocol import DriveState
from dob_hil.log import read_log
from dob_hil.loop.session import RunOptions, run_session
from firmware_sim.faulty_bus import FaultPlan, FaultyBus

from .odrive_support import NODE, odrive_config, tracking_rms

KT = 0.0827
EST_ID = NODE << 5 | CmdId.GET_ENCODER_ESTIMATES
TORQUE_ID = NODE << 5 | CmdId.SET_INPUT_TORQUE
N_FAULT = 300  # the period the timed faults happen at (0.3 s)
WATCHDOG_PERIODS = 10
HEARTBEAT_PERIODS = 10  # heartbeat_msg_rate_ms at 1 ms


def _msg(aid: int, data: bytes = b"", **kw: Any) -> can.Message:
    return can.Message(arbitration_id=aid, data=data, is_extended_id=kw.pop("is_extended_id", False), **kw)


BAD_FLOATS = tuple(
    _msg(EST_ID, struct.pack("<ff", pos, vel))
    for pos, vel in ((float("nan"), 0.0), (0.0, float("inf")), (-float("inf"), 1.0), (3e38, 0.0))
)
UNKNOWN_IDS = (
    _msg(0x7FF, b"\x01\x02\x03"),
    _msg(0x000, b"\x01\x01"),  # a CANopen NMT start
    _msg(0x18FF50E5, bytes(8), is_extended_id=True),
    _msg(NODE << 5 | 0x1F, bytes(8)),  # our node, a command this profile does not use
)
OTHER_NODES = (  # plausible frames of other ODrives: they must never reach the controller
    _msg((NODE + 1) << 5 | CmdId.GET_ENCODER_ESTIMATES, struct.pack("<ff", -77.7, 0.0)),
    _msg((NODE + 2) << 5 | CmdId.HEARTBEAT, codec.encode_heartbeat(Heartbeat(0x20, AxisState.IDLE))),
)
ERROR_FRAMES = (
    can.Message(is_error_frame=True, arbitration_id=0x20000004, data=bytes([0, 0x10, 0, 0, 0, 0, 0, 0])),
    can.Message(is_error_frame=True, arbitration_id=0x20000040, data=bytes(8)),  # bus off
)


@dataclass(frozen=True)
class Case:
    name: str
    plan: FaultPlan | None = None
    faults: dict[str, float | int] = field(default_factory=dict)
    completes: bool = True
    exit_match: str = "completed"
    events: dict[str, tuple[str, ...] | None] = field(default_factory=dict)
    trip: str = ""  # "", "drive_error" (truth shows the drive's error), "host_timeout"
    rms_factor: float = 1.5
    end: str = "stop"  # "stop": zero torque + IDLE sent last; "drive": the drive's watchdog idled it


def _loss(p: float, seed: int) -> FaultPlan:
    return FaultPlan(seed=seed, rx_match=EST_ID, drop_probability=p)


CASES = [
    Case("clean"),
    Case("estimates loss 1%", _loss(0.01, 2), events={"feedback_lost": None}),
    Case("estimates loss 10%", _loss(0.10, 3), events={"feedback_lost": None}, rms_factor=3.0),
    Case("duplicated estimates 2%", FaultPlan(seed=4, rx_match=EST_ID, duplicate_probability=0.02),
         events={"stale_feedback": ("duplicate",)}),
    Case("reordered estimates 2%", FaultPlan(seed=5, rx_match=EST_ID, delay_probability=0.02),
         events={"stale_feedback": ("delay",), "feedback_lost": None}),
    Case("wrong DLC 2%", FaultPlan(seed=8, rx_match=EST_ID, dlc_probability=0.02),
         events={"malformed_frame": ("dlc",), "feedback_lost": None}),
    Case("NaN, inf and huge estimates",
         FaultPlan(seed=9, rx_match=EST_ID, inject_every=21, inject=BAD_FLOATS),
         events={"malformed_frame": ("inject",)}),
    Case("unknown ids", FaultPlan(seed=9, rx_match=EST_ID, inject_every=49, inject=UNKNOWN_IDS),
         events={"foreign_frame": ("inject",)}),
    Case("other node ids", FaultPlan(seed=10, rx_match=EST_ID, inject_every=7, inject=OTHER_NODES),
         events={"foreign_frame": ("inject",)}),
    Case("error frames", FaultPlan(seed=11, rx_match=EST_ID, inject_every=27, inject=ERROR_FRAMES),
         events={"error_frame": ("inject_error",)}),
    Case("send raises from N on (bus off)",
         FaultPlan(tx_match=TORQUE_ID, send_fail_at=N_FAULT, send_fail_count=None,
                   send_fail_message="Bus off"),
         completes=False, exit_match="Bus off", events={"send_failed": ("send_fail",)}, trip="drive_error",
         end="drive"),
    # every host frame lost from N on (the FaultyBus window): no triggers, no torque inputs; the drive's
    # watchdog idles it and the host's timeout ends the run, both after 10 periods
    Case("host frames lost from N on (drive watchdog, host timeout)",
         FaultPlan(tx_match=TORQUE_ID, send_drop_at=N_FAULT, send_drop_count=None), completes=False,
         exit_match="host timeout", trip="drive_error", end="drive"),
    Case("drive fault at N", faults={"fault_at_s": 0.3}, completes=False,
         exit_match="axis error 0x00000020 (DRV_FAULT)", events={"drive_fault": None}, trip="drive_error"),
    Case("drive silent from N", faults={"silent_at_s": 0.3}, completes=False, exit_match="host timeout",
         trip="host_timeout"),
]  # fmt: skip


def _run(tmp_path: Path, case: Case) -> tuple[Any, FaultyBus | None, DobHilError | None]:
    extra = ""
    if case.faults:
        extra = "\n[sim.faults]\n" + "".join(f"{k} = {v!r}\n" for k, v in case.faults.items())
    config = odrive_config(tmp_path, extra=extra)
    holder: dict[str, FaultyBus] = {}

    def wrap(bus: can.BusABC) -> can.BusABC:
        assert case.plan is not None
        holder["bus"] = FaultyBus(bus, case.plan)
        return holder["bus"]

    error = None
    try:
        run_session(
            config, RunOptions(log_path=tmp_path / "run.mcap", bus_wrapper=wrap if case.plan else None)
        )
    except DobHilError as exc:
        error = exc
    return read_log(tmp_path / "run.mcap"), holder.get("bus"), error


@pytest.fixture(scope="module")
def clean_rms(tmp_path_factory: pytest.TempPathFactory) -> float:
    data, _, error = _run(tmp_path_factory.mktemp("clean"), CASES[0])
    assert error is None
    return tracking_rms(data)


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_fault_case(case: Case, tmp_path: Path, clean_rms: float) -> None:
    data, bus, error = _run(tmp_path, case)
    s = data.samples
    exit_reason = str(data.metadata["summary"]["exit_reason"])
    injected = dict(bus.counts()) if bus is not None else {}
    events: dict[str, int] = {}
    for e in data.events:
        events[str(e["kind"])] = events.get(str(e["kind"]), 0) + 1

    assert data.complete and not data.warnings
    assert case.exit_match in exit_reason, exit_reason
    assert (exit_reason == "completed") == case.completes == (error is None)
    if case.plan is not None and case.name != "clean":
        assert injected, "the plan injected nothing"

    # never beyond the current limit, in the samples and on the wire
    f = data.frames
    tx = f[(f["direction"] == 1) & (f["arbitration_id"] == TORQUE_ID)]
    torques = np.array([struct.unpack("<f", bytes(row[:4]))[0] for row in tx["data"]])
    assert np.all(np.isfinite(torques)) and np.all(np.abs(torques) / KT <= 0.7)
    assert np.all(np.abs(s["u_applied_a"]) <= 0.7)
    # no estimate of another node, and no non-finite one, reached the controller
    assert np.all(np.isfinite(s["position"])) and not np.any(np.isclose(s["position"], -77.7))

    for kind, sources in case.events.items():
        if sources is None:
            assert events.get(kind, 0) >= 1, (kind, events)
        else:
            want = sum(injected.get(src, 0) for src in sources)
            assert want > 0 and events.get(kind, 0) == want, (kind, events, injected)

    if case.completes:
        assert len(s) == 1000
        np.testing.assert_array_equal(s["seq"], np.arange(1000))
        assert tracking_rms(data) <= case.rms_factor * clean_rms
    truth = data.truth
    if case.trip == "drive_error":
        # the drive's error (truth: FAULT) came at most a watchdog timeout after N, and the host
        # stopped within one heartbeat period of it
        hit = np.flatnonzero(truth["drive_state"] == int(DriveState.FAULT))
        assert len(hit)
        error_period = int(truth["period_index"][hit[0]])
        assert N_FAULT <= error_period <= N_FAULT + WATCHDOG_PERIODS + 1
        if case.end != "drive" or "Bus off" not in case.exit_match:
            assert len(s) <= error_period + HEARTBEAT_PERIODS + 1
    elif case.trip == "host_timeout":
        assert len(s) == N_FAULT + 10 - 1 or len(s) == N_FAULT + 10

    host_tx = f[f["direction"] == 1]
    last = [(int(r["arbitration_id"]) & 0x1F, bytes(r["data"])) for r in host_tx[-2:]]
    if case.end == "stop":
        assert last == [(CmdId.SET_INPUT_TORQUE, bytes(8)), (CmdId.SET_AXIS_STATE, b"\x01" + bytes(7))]
    else:  # the stop could not be sent (bus off) or came after the drive's error: it idled itself
        assert truth["drive_state"][-1] == int(DriveState.FAULT)
