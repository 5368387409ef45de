"""One clock per log, the lockstep bus implementations, the stall count, [run] OS settings."""

from __future__ import annotations

import dataclasses
import gc
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from log_checks import assert_log_times_monotonic

from dob_hil.config import Config
from dob_hil.errors import DobHilError
from dob_hil.log import read_log
from dob_hil.loop.inproc_bus import InProcessBus, bus_pair
from dob_hil.loop.runners import _seq_delta, _unsequenced_periods
from dob_hil.loop.session import RunOptions, run_session

PERIOD_NS = 300_000


def test_lockstep_log_is_on_one_clock(paper_step: Config, log_path: Path) -> None:
    summary = run_session(paper_step, RunOptions(log_path=log_path, duration_s=0.2))
    times = assert_log_times_monotonic(log_path)
    data = read_log(log_path)
    s = data.samples
    end_ns = len(s) * PERIOD_NS + (paper_step.drive.watchdog_periods + 2) * PERIOD_NS
    # every channel on the simulated clock: within the run's simulated span, not hours away
    for topic, ts in times.items():
        assert ts[0] >= 0 and ts[-1] <= end_ns, (topic, ts[0], ts[-1])
    np.testing.assert_array_equal(s["rx_time_ns"], s["time_ns"])
    np.testing.assert_array_equal(s["tx_time_ns"], s["time_ns"])
    kinds = [e["kind"] for e in data.events]
    assert kinds[0] == "run_start" and kinds[-1] == "run_end"
    assert summary.exit_reason == "completed"


@pytest.mark.parametrize("impl", ["inprocess", "virtual"])
def test_both_lockstep_buses_give_the_same_run(paper_sine: Config, tmp_path: Path, impl: str) -> None:
    ref, other = tmp_path / "ref.mcap", tmp_path / f"{impl}.mcap"
    run_session(paper_sine, RunOptions(log_path=ref, duration_s=0.1, bus_impl="virtual"))
    run_session(paper_sine, RunOptions(log_path=other, duration_s=0.1, bus_impl=impl))
    a, b = read_log(ref), read_log(other)
    for name in ("counts", "x_hat", "u_cmd_a", "dac_counts", "time_ns"):
        np.testing.assert_array_equal(a.samples[name], b.samples[name])
    np.testing.assert_array_equal(a.frames["data"], b.frames["data"])
    assert read_log(other).metadata["run"]["mode"] == "lockstep"


def test_unknown_bus_impl_is_refused(paper_step: Config, log_path: Path) -> None:
    with pytest.raises(DobHilError, match="--bus-impl: expected one of inprocess, virtual, got 'x'"):
        run_session(paper_step, RunOptions(log_path=log_path, bus_impl="x"))
    with pytest.raises(DobHilError, match="--bus-impl"):
        bus_pair("c", "x")


def test_in_process_bus_hands_over_the_same_message() -> None:
    import can

    host, drive = bus_pair("t")
    assert isinstance(host, InProcessBus)
    msg = can.Message(arbitration_id=0x123, data=b"\x01\x02", is_extended_id=False)
    host.send(msg)
    assert drive.recv(0.0) is msg  # no copy
    assert drive.recv(1.0) is None and host.recv(0.0) is None  # nothing queued: at once
    drive.set_filters([{"can_id": 0x100, "can_mask": 0x7FF}])
    host.send(can.Message(arbitration_id=0x123, is_extended_id=False))
    host.send(can.Message(arbitration_id=0x100, is_extended_id=False))
    got = drive.recv(0.0)
    assert got is not None and got.arbitration_id == 0x100
    drive.set_filters(None)  # every frame again
    host.send(can.Message(arbitration_id=0x123, is_extended_id=False))
    got = drive.recv(0.0)
    assert got is not None and got.arbitration_id == 0x123
    host.shutdown()
    with pytest.raises(can.CanOperationError):
        host.send(msg)
    drive.shutdown()


@pytest.mark.parametrize("last_seq", [0, 100, 255])
@pytest.mark.parametrize("missing", [0, 1, 5, 127, 128, 200, 255, 256, 257, 300, 1000, 5000])
def test_a_stall_is_counted_from_time_beyond_the_sequence_range(last_seq: int, missing: int) -> None:
    """A host stall of ``missing`` periods after sample k - 1: the newest feedback comes
    ``missing + 1`` periods after k - 1's instant. The sequence difference plus the periods counted
    from time is ``missing``, also beyond the 8-bit range (where the sequence alone wraps)."""
    expected = (last_seq + 1) % 256
    seq = (last_seq + 1 + missing) % 256
    delta = _seq_delta(seq, expected)
    for jitter_ns in (-PERIOD_NS // 3, 0, PERIOD_NS // 3):
        since_ns = (missing + 1) * PERIOD_NS + jitter_ns
        gap, excess = _unsequenced_periods(delta, since_ns, PERIOD_NS)
        assert gap + excess == missing
        assert gap == missing % 256 and 0 <= gap < 256


def test_a_stale_frame_read_at_once_is_no_stall() -> None:
    assert _unsequenced_periods(_seq_delta(9, 11), PERIOD_NS, PERIOD_NS) == (-2, 0)


def test_a_drive_stalled_with_the_host_is_reported_not_filled() -> None:
    # the expected sequence number, 300 periods late: both sides stalled (a starved machine)
    assert _unsequenced_periods(0, 301 * PERIOD_NS, PERIOD_NS) == (0, 300)


def test_run_section_os_settings_are_applied(paper_step: Config, log_path: Path) -> None:
    run = dataclasses.replace(paper_step.run, freeze_gc=True, cpu_affinity=(0,))
    patient = dataclasses.replace(paper_step.drive, watchdog_periods=10_000, feedback_timeout_periods=10_000)
    config = dataclasses.replace(paper_step, run=run, drive=patient)
    was_enabled, cpus = gc.isenabled(), os.sched_getaffinity(0)
    summary = run_session(config, RunOptions(log_path=log_path, duration_s=0.05, realtime=True,
                                             enable_timeout_s=30.0))  # fmt: skip
    assert any("gc.freeze()" in a for a in summary.rt_applied), summary.rt_applied
    if sys.platform.startswith("linux"):
        assert any("CPU affinity [0]" in a for a in summary.rt_applied + summary.rt_refused)
    assert gc.isenabled() == was_enabled  # restored after the run
    assert os.sched_getaffinity(0) == cpus
