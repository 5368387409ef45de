"""Shared helpers of the fault tests: configs with faults, running a case, measuring it from the log."""

from __future__ import annotations

import collections
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np
import numpy.typing as npt

from dob_hil.config import Config, load_config
from dob_hil.errors import DobHilError
from dob_hil.link.protocol import DriveState, FrameKind
from dob_hil.log import LogData, read_log
from dob_hil.log.schemas import FLAG_FEEDBACK_MISSING
from dob_hil.loop.session import RunOptions, RunSummary, run_session
from dob_hil.scenarios import scenario_path
from firmware_sim.faulty_bus import FaultPlan, FaultyBus

LIMIT_CODE = 1433  # floor(0.7 A / (1/2048 A)) of paper-step
ENABLE_BIT = 0x80
CONTROL_DISABLE = 0


def config_text(
    *,
    node_id: int = 1,
    drive: dict[str, Any] | None = None,
    run: dict[str, Any] | None = None,
    faults: dict[str, Any] | None = None,
) -> str:
    """paper-step's TOML with drive keys replaced, run keys added and a ``[sim.faults]`` table."""
    text = scenario_path("paper-step").read_text()
    changes = {"node_id": node_id, **(drive or {})}
    for key, value in changes.items():
        text, n = re.subn(rf"(?m)^{key} = .*$", f"{key} = {_toml(value)}", text)
        if n == 0:
            text = text.replace("[drive]\n", f"[drive]\n{key} = {_toml(value)}\n")
    if run:
        text = text.replace("[run]\n", "[run]\n" + "".join(f"{k} = {_toml(v)}\n" for k, v in run.items()))
    if faults:
        text += "\n[sim.faults]\n" + "".join(f"{k} = {_toml(v)}\n" for k, v in faults.items())
    return text


def write_config(tmp_path: Path, name: str = "case", **kw: Any) -> tuple[Config, Path]:
    path = tmp_path / f"{name}.toml"
    path.write_text(config_text(**kw))
    return load_config(path), path


def _toml(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    return repr(value)


@dataclass
class CaseRun:
    summary: RunSummary | None
    error: DobHilError | None
    data: LogData
    bus: FaultyBus | None

    @property
    def exit_reason(self) -> str:
        return str(self.data.metadata["summary"]["exit_reason"])


def run_case(config: Config, log_path: Path, plan: FaultPlan | None = None, **options: Any) -> CaseRun:
    """run_session with an optional FaultyBus on the host's end; a DobHilError is kept, not raised."""
    holder: dict[str, FaultyBus] = {}

    def wrap(bus: can.BusABC) -> can.BusABC:
        assert plan is not None
        holder["bus"] = FaultyBus(bus, plan)
        return holder["bus"]

    summary: RunSummary | None = None
    error: DobHilError | None = None
    try:
        summary = run_session(
            config, RunOptions(log_path=log_path, bus_wrapper=wrap if plan else None, **options)
        )
    except DobHilError as exc:
        error = exc
    return CaseRun(summary, error, read_log(log_path), holder.get("bus"))


# --- measurements from the log ------------------------------------------------------------------
IntArray = npt.NDArray[np.int64]


def tx_frames(data: LogData, kind: FrameKind, node_id: int) -> npt.NDArray[np.void]:
    f = data.frames
    return f[(f["direction"] == 1) & (f["arbitration_id"] == kind + node_id)]


def rx_frames(data: LogData, kind: FrameKind, node_id: int) -> npt.NDArray[np.void]:
    f = data.frames
    return f[(f["direction"] == 0) & (f["arbitration_id"] == kind + node_id)]


def command_codes(data: LogData, node_id: int) -> IntArray:
    tx = tx_frames(data, FrameKind.COMMAND, node_id)
    return tx["data"][:, :2].copy().view("<i2")[:, 0].astype(np.int64)


def missing_runs(flags: npt.NDArray[np.uint8]) -> IntArray:
    """For each sample, how many samples in a row (up to and including it) had no feedback."""
    missing = (flags & FLAG_FEEDBACK_MISSING) != 0
    out = np.zeros(len(flags), dtype=np.int64)
    run = 0
    for i, m in enumerate(missing):
        run = run + 1 if m else 0
        out[i] = run
    return out


def event_counts(data: LogData) -> collections.Counter[str]:
    return collections.Counter(str(e["kind"]) for e in data.events)


def tracking_rms(data: LogData, from_s: float = 0.1) -> float:
    """RMS of reference minus the *true* position (ground truth), over samples after ``from_s``."""
    s, t = data.samples, data.truth
    by_period = {int(p): i for i, p in enumerate(t["period_index"])}
    idx = np.array([by_period[int(k)] for k in s["seq"]])
    window = s["time_ns"] >= from_s * 1e9
    err = s["x_ref"][window, 0] - t["state"][idx[window], 0]
    return float(np.sqrt(np.mean(err**2)))


def first_truth_period(data: LogData, state: DriveState, from_period: int = 0) -> int | None:
    t = data.truth
    hit = np.flatnonzero((t["drive_state"] == int(state)) & (t["period_index"] >= from_period))
    return int(t["period_index"][hit[0]]) if len(hit) else None


def ends_with_zero_and_disable(data: LogData, node_id: int) -> bool:
    """The run ended with the stop sequence (PROTOCOL.md "Stopping"): the last frame sent is CONTROL
    disable, and the last COMMAND is 0 A with the enable bit clear, unless the drive's last feedback
    said DISABLED (then the stop sends no COMMAND: a drive may fault on a COMMAND while DISABLED)."""
    f = data.frames
    tx = f[f["direction"] == 1]
    if not len(tx):
        return False
    end = tx[-1]
    if not (end["arbitration_id"] == FrameKind.CONTROL + node_id and end["data"][0] == CONTROL_DISABLE):
        return False
    cmd_rows = np.flatnonzero(tx["arbitration_id"] == FrameKind.COMMAND + node_id)
    if len(cmd_rows):
        last = tx[cmd_rows[-1]]
        if bytes(last["data"][:2]) == b"\x00\x00" and not last["data"][2] & ENABLE_BIT:
            return True
    rx = f[f["direction"] == 0]
    feedback = rx[rx["arbitration_id"] == FrameKind.FEEDBACK + node_id]
    return len(feedback) > 0 and not feedback["data"][-1, 5] & 0x03  # neither ENABLED nor FAULT


@dataclass
class Measured:
    """What one case did, for the assertions and for the report."""

    case: str
    exit_reason: str
    samples: int
    missing: int
    max_missing_run: int
    max_code: int  # largest |DAC code| in the samples and the raw COMMAND frames
    events: dict[str, int]
    injected: dict[str, int]
    trip_periods: int | None = None
    rms_error: float | None = None
    ended: str = ""
    notes: list[str] = field(default_factory=list)

    def row(self) -> str:
        ev = ", ".join(
            f"{k} {v}" for k, v in sorted(self.events.items()) if k not in ("run_start", "run_end")
        )
        inj = ", ".join(f"{k} {v}" for k, v in sorted(self.injected.items()))
        rms = "-" if self.rms_error is None else f"{self.rms_error:.4f}"
        trip = "-" if self.trip_periods is None else str(self.trip_periods)
        return (
            f"| {self.case} | {self.exit_reason[:60]} | {self.samples} | {self.missing}"
            f" | {self.max_missing_run} | {self.max_code} | {trip} | {rms} | {self.ended} | {inj} | {ev} |"
        )


RESULTS: list[Measured] = []
Check = Callable[[CaseRun, Measured], None]
