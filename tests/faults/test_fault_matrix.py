"""The fault matrix in lockstep: every case a whole run of paper-step (1 s, 3333 samples), checked
through its log.

Transport faults come from a seeded :class:`~firmware_sim.faulty_bus.FaultyBus` on the host's bus
end (``RunOptions.bus_wrapper``), drive faults from ``[sim.faults]``. For every case: no command
beyond the current limit (samples and raw COMMAND frames); samples without feedback follow the
missing-feedback policy and are bounded; every injected fault shows up as an event; the run either
completes and still tracks, or ends with a named exit reason and the drive at zero current, with
the number of periods from the fault to the trip measured and asserted.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from fault_support import (
    LIMIT_CODE,
    RESULTS,
    CaseRun,
    Measured,
    command_codes,
    ends_with_zero_and_disable,
    event_counts,
    first_truth_period,
    missing_runs,
    run_case,
    rx_frames,
    tracking_rms,
    write_config,
)

from dob_hil.link import protocol
from dob_hil.link.protocol import DriveState, FrameKind
from dob_hil.log.schemas import FLAG_FEEDBACK_MISSING
from firmware_sim.faulty_bus import FaultPlan

NODE = 1
FB_ID = FrameKind.FEEDBACK + NODE
CMD_ID = FrameKind.COMMAND + NODE
N_FAULT = 1000  # the period the timed faults happen at (0.3 s)
TIMEOUT_PERIODS = 10  # paper-step's drive.feedback_timeout_periods
WATCHDOG_PERIODS = 10  # paper-step's drive.watchdog_periods
MAX_MISSING = 3  # run.max_missing_periods default


def _msg(aid: int, data: bytes = b"", **kw: Any) -> can.Message:
    return can.Message(arbitration_id=aid, data=data, is_extended_id=kw.pop("is_extended_id", False), **kw)


UNKNOWN_IDS = (
    _msg(0x7FF, b"\x01\x02\x03"),
    _msg(0x000, b"\x01\x01"),  # a CANopen NMT start, not ours
    _msg(0x18FF50E5, bytes(8), is_extended_id=True),
    _msg(FB_ID, is_remote_frame=True, dlc=6),  # a remote request on our feedback id
)
OTHER_NODES = (  # plausible frames of other drives: they must never reach the controller
    _msg(
        FrameKind.FEEDBACK + 2,
        protocol.encode_feedback(protocol.FeedbackFrame(-777_777, 3, protocol.Status.ENABLED)),
    ),
    _msg(FrameKind.FAULT + 3, protocol.encode_fault(protocol.FaultFrame(protocol.FaultCode.OVERCURRENT, 0))),
    _msg(FrameKind.HEARTBEAT + 5, protocol.encode_heartbeat(protocol.HeartbeatFrame(DriveState.FAULT))),
    _msg(FrameKind.COMMAND + 2, bytes(3)),
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
    run: dict[str, Any] = field(default_factory=dict)
    completes: bool | None = True  # None: either (the outcome depends on what the corruption hit)
    exit_match: str = "completed"
    # event kind -> the FaultyBus record kinds whose total it must equal (None: at least one event)
    events: dict[str, tuple[str, ...] | None] = field(default_factory=dict)
    trip: str = ""  # "", "drive_fault", "host_timeout", "watchdog", "watchdog_after_stop", "send_failed"
    trip_periods: int | None = None
    rms_factor: float = 1.5  # completed runs: tracking RMS <= factor * the clean run's
    true_offset: float = 0.0  # completed runs: the true position settles this far from the measured
    end: str = "stop"  # "stop": zero COMMAND + disable sent last; "watchdog": the drive's watchdog


def _loss(p: float, seed: int) -> FaultPlan:
    return FaultPlan(seed=seed, rx_match=FB_ID, drop_probability=p)


CASES = [
    Case("clean"),
    Case("feedback loss 0.1%", _loss(0.001, 1), events={"feedback_lost": None}),
    Case("feedback loss 1%", _loss(0.01, 2), events={"feedback_lost": None}),
    Case("feedback loss 10%", _loss(0.10, 3), events={"feedback_lost": None}, rms_factor=3.0),
    Case("feedback loss 10%, policy zero", _loss(0.10, 3), run={"missing_feedback_policy": "zero"},
         events={"feedback_lost": None}, rms_factor=3.0),
    Case("feedback loss 10%, policy extrapolate", _loss(0.10, 3),
         run={"missing_feedback_policy": "extrapolate"}, events={"feedback_lost": None}, rms_factor=3.0),
    Case("duplicated feedback 2%", FaultPlan(seed=4, rx_match=FB_ID, duplicate_probability=0.02),
         events={"stale_feedback": ("duplicate",)}),
    Case("reordered feedback 2% (swapped)", FaultPlan(seed=5, rx_match=FB_ID, delay_probability=0.02),
         events={"stale_feedback": ("delay",), "feedback_lost": None}),
    Case("late feedback 2% (2 Ts)", FaultPlan(seed=6, rx_match=FB_ID, delay_probability=0.02, delay_frames=2),
         events={"stale_feedback": ("delay",), "feedback_lost": None}),
    Case("corrupted feedback 2% (reserved bits)",
         FaultPlan(seed=7, rx_match=FB_ID, corrupt_probability=0.02, corrupt_xor=bytes(5) + b"\x80"),
         events={"malformed_frame": ("corrupt",), "feedback_lost": None}),
    Case("corrupted feedback 0.5% (random bytes)",
         FaultPlan(seed=12, rx_match=FB_ID, corrupt_probability=0.005), completes=None, exit_match=""),
    Case("wrong DLC 2%", FaultPlan(seed=8, rx_match=FB_ID, dlc_probability=0.02),
         events={"malformed_frame": ("dlc",), "feedback_lost": None}),
    Case("unknown ids", FaultPlan(seed=9, rx_match=FB_ID, inject_every=50, inject=UNKNOWN_IDS),
         events={"foreign_frame": ("inject",)}),
    Case("other node ids", FaultPlan(seed=10, rx_match=FB_ID, inject_every=7, inject=OTHER_NODES),
         events={"foreign_frame": ("inject",)}),
    Case("error frames", FaultPlan(seed=11, rx_match=FB_ID, inject_every=25, inject=ERROR_FRAMES),
         events={"error_frame": ("inject_error",)}),
    Case("send raises once (buffer full)",
         FaultPlan(tx_match=CMD_ID, send_fail_at=N_FAULT, send_fail_count=1),
         completes=False, exit_match="Transmit buffer full", events={"send_failed": ("send_fail",)},
         trip="send_failed", trip_periods=0),
    Case("send raises from N on (bus off)",
         FaultPlan(tx_match=CMD_ID, send_fail_at=N_FAULT, send_fail_count=None, send_fail_message="Bus off"),
         completes=False, exit_match="Bus off", events={"send_failed": ("send_fail",)},
         trip="watchdog_after_stop", trip_periods=WATCHDOG_PERIODS, end="watchdog"),
    Case("commands lost from N on (drive watchdog)",
         FaultPlan(tx_match=CMD_ID, send_drop_at=N_FAULT, send_drop_count=None),
         completes=False, exit_match="the drive reports a fault", events={"drive_fault": None},
         trip="watchdog", trip_periods=WATCHDOG_PERIODS, end="watchdog"),
    Case("drive fault at N", faults={"fault_at_s": 0.3}, completes=False,
         exit_match="the drive reports a fault", events={"drive_fault": None, "drive_state": None},
         trip="drive_fault", trip_periods=0),
    Case("drive silent from N", faults={"silent_at_s": 0.3}, completes=False, exit_match="host timeout",
         trip="host_timeout", trip_periods=TIMEOUT_PERIODS),
    # an implausible encoder step trips the safety envelope (safety.max_encoder_jumps = 0 by default)
    Case("encoder jump at N (+20000 counts, 16-bit)", drive={"encoder_bits": 16},
         faults={"encoder_jump_at_s": 0.3, "encoder_jump_counts": 20000}, completes=False,
         exit_match="safety envelope: 1 encoder jump(s)", events={"encoder_jump": None}),
]  # fmt: skip


@pytest.fixture(scope="module")
def clean_rms(tmp_path_factory: pytest.TempPathFactory) -> float:
    tmp = tmp_path_factory.mktemp("clean")
    config, _ = write_config(tmp)
    return tracking_rms(run_case(config, tmp / "clean.mcap").data)


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_fault_case(case: Case, tmp_path: Path, clean_rms: float) -> None:
    config, _ = write_config(tmp_path, drive=case.drive, run=case.run, faults=case.faults)
    r = run_case(config, tmp_path / "run.mcap", case.plan)
    data = r.data
    s = data.samples
    injected = dict(r.bus.counts()) if r.bus is not None else {}
    events = event_counts(data)
    runs = missing_runs(s["flags"])
    codes_tx = command_codes(data, NODE)
    m = Measured(
        case=case.name,
        exit_reason=r.exit_reason,
        samples=len(s),
        missing=int(np.count_nonzero(s["flags"] & FLAG_FEEDBACK_MISSING)),
        max_missing_run=int(runs.max(initial=0)),
        max_code=int(max(np.abs(s["dac_counts"]).max(initial=0), np.abs(codes_tx).max(initial=0))),
        events=dict(events),
        injected=injected,
    )
    RESULTS.append(m)

    # the log is finished and says why the run ended
    assert data.complete and not data.warnings
    assert case.exit_match in m.exit_reason
    completed = m.exit_reason == "completed"
    assert completed == (r.error is None)
    if case.completes is not None:
        assert completed == case.completes
    if case.plan is not None and case.name != "clean":
        assert injected, "the plan injected nothing"

    # never beyond the current limit, in the samples and on the wire
    assert m.max_code <= LIMIT_CODE
    assert np.all(np.abs(s["u_applied_a"]) <= 0.7)

    _check_missing_policy(r, case, runs)
    _check_events(case, events, injected)
    if completed:
        assert len(s) == 3333
        np.testing.assert_array_equal(s["seq"], np.arange(3333))
        m.rms_error = tracking_rms(data)
        assert m.rms_error <= case.rms_factor * clean_rms, (m.rms_error, clean_rms)
        # the measured position settles on the reference; the true one by true_offset from it
        tail = (np.arange(len(s)) >= len(s) - 600) & (runs == 0)  # measured samples of the last 0.18 s
        true_pos = data.truth["state"][: len(s), 0]
        assert np.max(np.abs(s["x_ref"][tail, 0] - s["position"][tail, 0])) < 0.06  # 4.8 % overshoot
        assert np.max(np.abs(true_pos[tail] - s["position"][tail, 0] - case.true_offset)) < 0.001
    _check_trip(r, case, m)
    _check_end(r, case, m)


def _check_missing_policy(r: CaseRun, case: Case, runs: np.ndarray) -> None:
    """Lockstep: a sample without feedback is substituted (hold/extrapolate/zero) for at most
    max_missing_periods in a row, then commands zero; the host timeout ends a longer gap."""
    s = r.data.samples
    policy = case.run.get("missing_feedback_policy", "hold")
    missing = runs > 0
    assert runs.max(initial=0) < TIMEOUT_PERIODS  # the host timeout trips at the 10th
    beyond = runs > MAX_MISSING
    assert np.all(s["dac_counts"][beyond] == 0)
    if policy == "zero":
        assert np.all(s["dac_counts"][missing] == 0)
    if policy == "hold":
        # the estimator was given the last measured position again
        for i in np.flatnonzero(missing & (np.arange(len(s)) > 0)):
            last = i - runs[i]
            if last >= 0:
                assert s["position"][i, 0] == s["position"][last, 0]
    # every measurement the controller used came in a FEEDBACK frame of our node, none from another
    assert not np.any(s["counts"] == -777_777)
    ours = rx_frames(r.data, FrameKind.FEEDBACK, NODE)
    raw = set(ours["data"][:, :4].copy().view("<i4")[:, 0].tolist())
    span = 2 ** case.drive.get("encoder_bits", 32)  # the link unwraps; compare modulo the counter
    used = {int(c) % span for c in s["counts"][~missing, 0]}
    assert used <= {c % span for c in raw}
    # each gap is a feedback_lost event (logged when feedback resumes) covering its samples
    lost = [e for e in r.data.events if e["kind"] == "feedback_lost"]
    gap_total = sum(int(e["data"]["count"]) for e in lost)
    open_gap = int(runs[-1]) if len(runs) else 0  # a gap the run ended in has no such event
    assert gap_total + open_gap == int(np.count_nonzero(missing))


def _check_events(case: Case, events: Any, injected: dict[str, int]) -> None:
    for kind, sources in case.events.items():
        if sources is None:
            assert events.get(kind, 0) >= 1, (kind, events)
        else:
            want = sum(injected.get(src, 0) for src in sources)
            assert want > 0
            assert events.get(kind, 0) == want, (kind, events, injected)


def _check_trip(r: CaseRun, case: Case, m: Measured) -> None:
    s, data = r.data.samples, r.data
    trip_k = len(s)  # the sample the run stopped at (never logged)
    if case.trip == "drive_fault":
        m.trip_periods = trip_k - N_FAULT  # FAULT status in the feedback of sample N
    elif case.trip == "host_timeout":
        m.trip_periods = trip_k - N_FAULT + 1  # periods without feedback, the tripping one included
        assert np.all(s["flags"][N_FAULT:] & FLAG_FEEDBACK_MISSING)
    elif case.trip == "send_failed":
        m.trip_periods = trip_k - N_FAULT  # the COMMAND answering sample N failed
    elif case.trip == "watchdog":
        fault_period = first_truth_period(data, DriveState.FAULT)
        assert fault_period is not None
        m.trip_periods = fault_period - N_FAULT  # periods without a command, the tripping one included
        assert trip_k == fault_period  # the host stopped on the feedback that reported it
    elif case.trip == "watchdog_after_stop":
        fault_period = first_truth_period(data, DriveState.FAULT)
        assert fault_period is not None, "the drive never left ENABLED"
        m.trip_periods = fault_period - N_FAULT
        assert trip_k == N_FAULT
    if case.trip_periods is not None:
        assert m.trip_periods == case.trip_periods, m


def _check_end(r: CaseRun, case: Case, m: Measured) -> None:
    data = r.data
    if case.end == "stop":
        assert ends_with_zero_and_disable(data, NODE)
        m.ended = "zero + disable sent"
    else:
        # the stop could not be sent (bus off) or came after the drive faulted: the drive's
        # watchdog put it in FAULT, which cuts the current
        assert data.truth["drive_state"][-1] == int(DriveState.FAULT)
        m.ended = "drive watchdog FAULT"
        if "send_fail" in m.injected:
            assert m.events.get("send_failed", 0) >= 3  # the failed command and both stop frames
