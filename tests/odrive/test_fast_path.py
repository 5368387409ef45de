"""The ODrive profile's lockstep fast paths give exactly the records of the general path.

``firmware_sim.odrive.clocks.FAST_PATH`` (the simulated ODrive: Set_Input_Torque and the RTR
inline, a host-clocked period and its estimates in one call) and ``dob_hil.link.odrive.link.FAST_PATH``
(the link: the RTR's answer, quantize, Set_Input_Torque) are switched off to force the general
path; both runs must log the same samples (but compute time), frames, ground truth and events,
end the same way, and the fast run must really have taken the fast paths. Three levels:
whole lockstep sessions (errors injected by the drive, estimates lost, encoder noise, bad frames,
a drive watchdog expiry), a scripted frame sequence against the simulated ODrive alone (bad torque
frames, a watchdog expiry, Clear_Errors and re-enabling mid-run, other control modes, a lost
trigger, both clockings), and the quantizer against :class:`TorqueQuantizer` for any current.
"""

from __future__ import annotations

import dataclasses
import math
import struct
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import firmware_sim.odrive.clocks as drive_clocks
from dob_hil.config import Config, DriveConfig
from dob_hil.errors import DobHilError
from dob_hil.link.odrive import codec
from dob_hil.link.odrive import link as odrive_link
from dob_hil.link.odrive.codec import AxisState, CmdId, ControlMode, InputMode, ODriveError
from dob_hil.link.odrive.link import OdriveDriveLink, TorqueQuantizer
from dob_hil.link.odrive.options import OdriveOptions, odrive_options
from dob_hil.log import read_log
from dob_hil.loop.inproc_bus import bus_pair
from dob_hil.loop.session import RunOptions, run_session
from firmware_sim.faulty_bus import FaultPlan, FaultyBus
from firmware_sim.odrive import SimulatedOdrive

from .odrive_support import NODE, odrive_config
from .test_fault_matrix import BAD_FLOATS, EST_ID, TORQUE_ID

KT = 0.0827
LIMIT_A = 0.7


def _force_general(monkeypatch: pytest.MonkeyPatch, general: bool) -> None:
    monkeypatch.setattr(drive_clocks, "FAST_PATH", not general)
    monkeypatch.setattr(odrive_link, "FAST_PATH", not general)


class _Counts:
    """How often the fast paths ran (counting wrappers around them)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.periods = 0
        self.answers = 0
        self.commands = 0
        period_fast = drive_clocks.OdriveLockstep._period_fast
        estimates_fast = OdriveDriveLink._estimates_fast
        send_command = OdriveDriveLink.send_command

        def count_period(clock: drive_clocks.OdriveLockstep) -> None:
            self.periods += 1
            period_fast(clock)

        def count_answer(link: OdriveDriveLink, msg: can.Message, now_ns: int) -> bool:
            taken = estimates_fast(link, msg, now_ns)
            self.answers += taken
            return taken

        def count_command(link: OdriveDriveLink, codes: tuple[int, ...], answers_seq: int) -> int:
            self.commands += codes is link._q_codes
            return send_command(link, codes, answers_seq)

        monkeypatch.setattr(drive_clocks.OdriveLockstep, "_period_fast", count_period)
        monkeypatch.setattr(OdriveDriveLink, "_estimates_fast", count_answer)
        monkeypatch.setattr(OdriveDriveLink, "send_command", count_command)


# --- whole sessions ------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class SessionCase:
    name: str
    sim: dict[str, Any] = dataclasses.field(default_factory=dict)
    faults: dict[str, float | int] = dataclasses.field(default_factory=dict)
    plan: FaultPlan | None = None
    drive: dict[str, Any] = dataclasses.field(default_factory=dict)


SESSION_CASES = [
    SessionCase("clean"),
    SessionCase("noise and loss", sim={"noise_counts_std": 2.0, "loss_probability": 0.05, "seed": 7}),
    SessionCase("drive fault", faults={"fault_at_s": 0.2}),
    SessionCase("encoder jump", faults={"encoder_jump_at_s": 0.1, "encoder_jump_counts": 40}),
    SessionCase("drive silent", faults={"silent_at_s": 0.2}),
    # every Set_Input_Torque lost from 200 on: the drive's watchdog expires, the host stops on its heartbeat
    SessionCase("watchdog expiry",
                plan=FaultPlan(tx_match=TORQUE_ID, send_drop_at=200, send_drop_count=None)),
    # three triggers lost on the bus: the drive's time runs on (advance_period), the host fills the gap
    SessionCase("lost triggers", plan=FaultPlan(tx_match=EST_ID, send_drop_at=150, send_drop_count=3)),
    SessionCase("bad estimates", plan=FaultPlan(
        seed=3, rx_match=EST_ID, duplicate_probability=0.03, delay_probability=0.03, dlc_probability=0.03,
        drop_probability=0.03, inject_every=37, inject=BAD_FLOATS)),
    SessionCase("saturating", drive={"current_limit_A": 0.05}),
]  # fmt: skip


def _session_config(tmp_path: Path, case: SessionCase) -> Config:
    extra = ""
    if case.faults:
        extra = "\n[sim.faults]\n" + "".join(f"{k} = {v!r}\n" for k, v in case.faults.items())
    config = odrive_config(tmp_path, drive=case.drive, extra=extra)
    return dataclasses.replace(config, sim=dataclasses.replace(config.sim, **case.sim))


_LINK_INIT, _DRIVE_INIT = OdriveDriveLink.__init__, SimulatedOdrive.__init__
SUMMARY_KEYS = (
    "exit_reason",
    "samples",
    "saturated_samples",
    "missing_samples",
    "max_abs_current_A",
    "events",
)


def _session_records(
    tmp_path: Path, case: SessionCase, tag: str, monkeypatch: pytest.MonkeyPatch
) -> dict[str, Any]:
    config = _session_config(tmp_path, case)
    path = tmp_path / f"{tag}.mcap"
    links: list[OdriveDriveLink] = []  # the link and the drive built, for their counters

    def init_link(link: OdriveDriveLink, *args: Any, **kw: Any) -> None:
        _LINK_INIT(link, *args, **kw)
        links.append(link)

    monkeypatch.setattr(OdriveDriveLink, "__init__", init_link)
    drives: list[SimulatedOdrive] = []

    def init_drive(drive: SimulatedOdrive, *args: Any, **kw: Any) -> None:
        _DRIVE_INIT(drive, *args, **kw)
        drives.append(drive)

    monkeypatch.setattr(SimulatedOdrive, "__init__", init_drive)

    def wrap(bus: can.BusABC) -> can.BusABC:
        assert case.plan is not None
        return FaultyBus(bus, case.plan)

    error = None
    try:
        run_session(
            config, RunOptions(duration_s=0.4, log_path=path, bus_wrapper=wrap if case.plan else None)
        )
    except DobHilError as exc:
        error = str(exc)
    data = read_log(path)
    s = data.samples
    records: dict[str, Any] = {f"samples.{n}": s[n].tobytes() for n in s.dtype.names if n != "compute_ns"}
    records.update(
        frames=data.frames.tobytes(), fd_frames=data.fd_frames.tobytes(), truth=data.truth.tobytes()
    )
    records["events"] = [sorted((k, v) for k, v in e.items() if k != "wall_time_ns") for e in data.events]
    records["error"] = error
    summary = data.metadata["summary"]
    records["summary"] = [summary[key] for key in SUMMARY_KEYS]
    records["exit_reason"] = summary["exit_reason"]
    records["stats"] = [link.stats for link in links] + [drive.stats for drive in drives]
    records["n"] = (len(s), len(data.frames), len(data.truth))
    return records


@pytest.mark.parametrize("case", SESSION_CASES, ids=[c.name for c in SESSION_CASES])
def test_session_fast_equals_general(
    case: SessionCase, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _force_general(monkeypatch, True)
    general = _session_records(tmp_path, case, "general", monkeypatch)
    _force_general(monkeypatch, False)
    counts = _Counts(monkeypatch)
    fast = _session_records(tmp_path, case, "fast", monkeypatch)
    assert fast["n"] == general["n"]
    assert fast["exit_reason"] == general["exit_reason"] and fast["error"] == general["error"]
    for key in general:
        assert fast[key] == general[key], key
    n_samples = general["n"][0]
    assert n_samples >= 150 and len(general["stats"]) == 2
    # the fast paths carried the run (the general path only around what was unusual)
    # (a lost trigger's period is run by the runner's advance_period, and the next RTR closes the
    # next period again: tests/odrive/test_lost_trigger.py)
    assert counts.periods >= n_samples - 20
    assert counts.commands >= n_samples // 2
    assert counts.answers >= n_samples // 2


# --- the simulated ODrive alone, scripted --------------------------------------------------------
def _frame(cmd: CmdId, data: bytes = b"", *, node: int = NODE, **kw: Any) -> can.Message:
    return can.Message(arbitration_id=node << 5 | cmd, data=data, is_extended_id=False, **kw)


def _torque(torque_Nm: float) -> can.Message:
    return _frame(CmdId.SET_INPUT_TORQUE, struct.pack("<f4x", torque_Nm))


RTR = _frame(CmdId.GET_ENCODER_ESTIMATES, is_remote_frame=True, dlc=8)
ENABLE = [
    _frame(CmdId.SET_CONTROLLER_MODE, codec.encode_set_controller_mode(ControlMode.TORQUE_CONTROL,
                                                                       InputMode.PASSTHROUGH)),
    _torque(0.0),
    _frame(CmdId.SET_AXIS_STATE, codec.encode_set_axis_state(AxisState.CLOSED_LOOP_CONTROL)),
]  # fmt: skip
Step = list[can.Message] | str  # frames for one service() call, or "advance" (a lost trigger)


def _script() -> Iterator[Step]:
    yield ENABLE
    yield [RTR]
    for k in range(25):  # the ordinary period: the torque, then the next trigger
        yield [_torque(0.004 * math.sin(k / 3.0)), RTR]
    yield [_torque(1.0), RTR]  # beyond the current limit: the drive clamps it
    yield [_torque(-1.0), RTR]
    yield [_torque(float("nan")), RTR]  # a bad torque input: ignored
    yield [_frame(CmdId.SET_INPUT_TORQUE, bytes(4)), RTR]  # short
    yield [_frame(CmdId.SET_INPUT_TORQUE, bytes(8), is_remote_frame=True), RTR]
    yield [can.Message(arbitration_id=NODE << 5 | CmdId.SET_INPUT_TORQUE, data=bytes(8)), RTR]  # 29-bit
    yield [can.Message(is_error_frame=True, arbitration_id=NODE << 5 | CmdId.SET_INPUT_TORQUE, data=bytes(8))]
    yield [_torque(0.002), _frame(CmdId.SET_INPUT_TORQUE, bytes(8), node=NODE + 1), RTR]  # another node
    yield [_torque(0.003), _torque(-0.003), RTR]  # two torque inputs in one period: the last one acts
    yield [_torque(0.003), RTR, RTR]  # a second trigger in the same service() call
    yield "advance"  # a trigger lost on the bus: the drive's time runs on
    yield [_torque(0.001), RTR]
    yield [_frame(CmdId.SET_CONTROLLER_MODE, codec.encode_set_controller_mode(ControlMode.VELOCITY_CONTROL,
                                                                              InputMode.PASSTHROUGH)),
           _torque(0.01), RTR]  # fmt: skip
    yield [_torque(0.01), RTR]  # not in torque mode: zero current
    yield [ENABLE[0], _torque(0.01), RTR]
    for _ in range(13):  # triggers without torque inputs: the watchdog expires after 10 periods
        yield [RTR]
    yield [_torque(0.01), RTR]  # IDLE with an axis error: held as the input, not applied
    yield [_frame(CmdId.CLEAR_ERRORS, codec.encode_clear_errors(0)), RTR]
    yield [ENABLE[2], RTR]  # closed loop again, mid-run
    for k in range(15):
        yield [_torque(-0.003 * math.cos(k / 2.0)), RTR]
    yield [_frame(CmdId.SET_AXIS_STATE, codec.encode_set_axis_state(AxisState.IDLE)), _torque(0.01), RTR]
    yield [ENABLE[2], _torque(0.002), RTR]
    for k in range(12):
        yield [_torque(0.001 * k), RTR]


def _cyclic_script() -> Iterator[Step]:
    """The drive-clocked variant: the estimates are cyclic, a torque input closes the period."""
    yield ENABLE
    for k in range(20):
        yield [_torque(0.004 * math.sin(k / 3.0))]
    yield [_torque(float("nan")), RTR, _torque(0.001)]
    for _ in range(3):
        yield "advance"
    yield [_torque(0.001)]
    for _ in range(12):
        yield "advance"  # no torque inputs: the watchdog expires
    yield [_frame(CmdId.CLEAR_ERRORS, codec.encode_clear_errors(0)), ENABLE[2]]
    for k in range(10):
        yield [_torque(-0.002 * k)]


def _drive_records(config: Config, script: Callable[[], Iterator[Step]]) -> dict[str, Any]:
    host, drive_end = bus_pair("fast-path-test")
    truth: list[Any] = []
    drive = SimulatedOdrive(drive_end, config, truth_sink=truth.append)
    out: list[tuple[Any, ...]] = []
    serviced: list[int] = []
    for step in script():
        if step == "advance":
            drive.advance_period()
        else:
            for msg in step:
                host.send(msg)
            serviced.append(drive.service())
        while (msg := host.recv(0.0)) is not None:
            out.append((msg.timestamp, msg.arbitration_id, msg.is_remote_frame, msg.dlc, bytes(msg.data)))
    records = {"frames": out, "truth": truth, "serviced": serviced, "stats": drive.stats,
               "state": (drive.period_index, drive.time_ns, drive.true_state, drive.axis_error)}  # fmt: skip
    host.shutdown()
    drive_end.shutdown()
    return records


DRIVE_CASES = {
    "host-clocked": ({}, {}, _script),
    "host-clocked, noise and loss": ({"noise_counts_std": 3.0, "loss_probability": 0.1, "seed": 5}, {},
                                     _script),
    "host-clocked, injected faults": ({}, {"encoder_jump_at_s": 0.01, "encoder_jump_counts": 7,
                                           "fault_at_s": 0.06}, _script),
    "host-clocked, silent": ({}, {"silent_at_s": 0.02}, _script),
    "drive-clocked": ({"noise_counts_std": 1.0, "loss_probability": 0.1}, {}, _cyclic_script),
}  # fmt: skip


@pytest.mark.parametrize("name", list(DRIVE_CASES))
def test_drive_fast_equals_general(name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    sim, faults, script = DRIVE_CASES[name]
    extra = "\n[sim.faults]\n" + "".join(f"{k} = {v!r}\n" for k, v in faults.items()) if faults else ""
    config = odrive_config(tmp_path, extra=extra, cyclic=script is _cyclic_script)
    config = dataclasses.replace(config, sim=dataclasses.replace(config.sim, **sim))
    _force_general(monkeypatch, True)
    general = _drive_records(config, script)
    _force_general(monkeypatch, False)
    counts = _Counts(monkeypatch)
    fast = _drive_records(config, script)
    assert fast["frames"] == general["frames"]
    assert fast["truth"] == general["truth"]
    assert fast == general
    stats = general["stats"]
    # the script went where it was meant to: clamped and bad torque inputs, the watchdog, errors
    assert stats.heartbeats_sent >= 3 and stats.bad_frames >= 1 and stats.commands_accepted >= 30
    if script is _script:
        assert stats.saturations >= 2 and stats.bad_frames >= 2 and stats.frames_ignored >= 3
        assert counts.periods >= 60
    if "silent_at_s" in faults:
        assert stats.frames_suppressed >= 60
    elif script is _script:
        heartbeats = [f[4] for f in general["frames"] if f[1] == NODE << 5 | CmdId.HEARTBEAT]
        errors = {codec.decode_heartbeat(hb).axis_error for hb in heartbeats}
        assert ODriveError.WATCHDOG_TIMER_EXPIRED in errors  # the watchdog expired, was cleared
        assert 0 in errors  # ... and the axis ran on after Clear_Errors
        if "fault_at_s" in faults:
            assert ODriveError.DRV_FAULT in errors and general["state"][3] == ODriveError.DRV_FAULT


# --- the quantizer --------------------------------------------------------------------------------
def _make_link(bus: can.BusABC, limit_A: float, kt: float) -> OdriveDriveLink:
    drive = DriveConfig(profile="odrive", node_id=NODE, current_limit_A=limit_A)
    return OdriveDriveLink(
        bus, drive, OdriveOptions(torque_constant_Nm_per_A=kt, encoder_cpr=10000), 1_000_000
    )


@contextmanager
def _links(n: int, limit_A: float = LIMIT_A, kt: float = KT) -> Iterator[list[OdriveDriveLink]]:
    """``n`` links on buses of their own, shut down afterwards."""
    pairs = [bus_pair(f"fast-path-quantize-{i}") for i in range(n)]
    try:
        yield [_make_link(host, limit_A, kt) for host, _ in pairs]
    finally:
        for pair in pairs:
            for bus in pair:
                bus.shutdown()


CURRENTS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(min_value=-0.8, max_value=0.8),
    st.sampled_from([0.0, -0.0, LIMIT_A, -LIMIT_A, math.nextafter(LIMIT_A, 0.0), math.nextafter(LIMIT_A, 1.0),
                     5e-324, -1e-40, 1e-45]),
)  # fmt: skip


@given(u=CURRENTS)
def test_quantize_fast_equals_general(u: float) -> None:
    with _links(2) as (fast_link, general_link):
        _quantize_fast_equals_general(u, fast_link, general_link)


def _quantize_fast_equals_general(
    u: float, fast_link: OdriveDriveLink, general_link: OdriveDriveLink
) -> None:
    general_link.fast = False
    reference = TorqueQuantizer(LIMIT_A, KT).quantize((u,))
    fast = fast_link.quantize((u,))
    assert fast == general_link.quantize((u,)) == reference
    assert [struct.pack("<d", v) for v in fast[1]] == [struct.pack("<d", v) for v in reference[1]]  # -0.0 too
    # the Set_Input_Torque payload is the general path's, whether quantize's codes are passed or a copy
    payloads = []
    for link, codes in ((fast_link, fast[0]), (general_link, tuple(fast[0]))):
        sent: list[can.Message] = []
        link._frame_hook = lambda msg, is_rx: sent.append(msg)  # noqa: B023
        link.send_command(codes, 0)
        payloads.append((sent[0].arbitration_id, sent[0].dlc, bytes(sent[0].data)))
    assert payloads[0] == payloads[1]
    torque, _ = TorqueQuantizer(LIMIT_A, KT).torque_of(fast[0][0])
    assert payloads[0][2] == struct.pack("<f4x", torque)


def test_quantize_tiny_limit_takes_the_general_path() -> None:
    """A current whose float32 torque maps back beyond the limit is stepped one ulp towards zero
    (the general path); the fast path never sends it unstepped."""
    for limit_A, kt in ((0.1, 0.3), (0.7, 0.0827), (1.0 / 3.0, 0.1), (2.5e-3, 7.0)):
        ref = TorqueQuantizer(limit_A, kt)
        with _links(1, limit_A, kt) as (link,):
            for u in (limit_A, -limit_A, math.nextafter(limit_A, 0.0), limit_A * 0.999999):
                codes, applied, saturated = link.quantize((u,))
                assert (codes, applied, saturated) == ref.quantize((u,))
                assert abs(applied[0]) <= limit_A


def test_general_switch_reaches_both_sides(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """FAST_PATH = False is read when the drive's clock and the link are built."""
    config = odrive_config(tmp_path)
    _force_general(monkeypatch, True)
    buses = [*bus_pair("fast-path-switch"), *bus_pair("fast-path-switch-2")]
    try:
        drive = SimulatedOdrive(buses[1], config)
        link = OdriveDriveLink(buses[0], config.drive, odrive_options(config), config.plant.period_ns)
        assert drive._lockstep is not None and not drive._lockstep.fast and not link.fast
        _force_general(monkeypatch, False)
        assert SimulatedOdrive(buses[3], config)._lockstep.fast  # type: ignore[union-attr]
        assert np.isfinite(link.quantize((0.1,))[1][0])
    finally:
        for bus in buses:
            bus.shutdown()
