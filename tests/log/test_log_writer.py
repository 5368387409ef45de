"""LogWriter: errors that name what is wrong, bounded backlog with counted drops, failures surface."""

from __future__ import annotations

import os
import resource
import signal
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from log_checks import CallClock

from dob_hil.errors import DobHilError
from dob_hil.log import LogLayout, LogWriteError, LogWriter, read_log
from dob_hil.log.bench import SyntheticRun
from dob_hil.log.check import assert_complete, check_sequences
from dob_hil.log.schemas import CAN_FLAG_EXTENDED, CAN_FLAG_FD, CAN_FLAG_REMOTE, CAN_RX, CAN_TX

LAYOUT = LogLayout(2, 1, 1, 2)
GOOD = dict(
    time_ns=0, rx_time_ns=1, tx_time_ns=2, lateness_ns=1, counts=(1,), position=(0.5,), x_ref=(1.0, 2.0),
    x_hat=(1.0, 2.0), x_bar=(1.0, 2.0), u_fb=(0.1,), u_dist=(0.2,), u_cmd_A=(0.3,), u_applied_A=(0.3,), seq=0,
    compute_ns=100, dac_counts=(300,), feedback_seq=0, flags=0,
)  # fmt: skip


def test_missing_directory_fails_at_construction(tmp_path: Path) -> None:
    with pytest.raises(LogWriteError, match="does not exist"):
        LogWriter(tmp_path / "nope" / "run.mcap", LAYOUT)


def test_directory_as_path_fails_at_construction(tmp_path: Path) -> None:
    with pytest.raises(LogWriteError, match="is a directory"):
        LogWriter(tmp_path, LAYOUT)


def test_disk_full_at_open_names_the_cause() -> None:
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full on this system")
    with pytest.raises(LogWriteError, match="No space left on device"):
        LogWriter(Path("/dev/full"), LAYOUT)


def test_record_errors_name_the_field(tmp_path: Path) -> None:
    with LogWriter(tmp_path / "x.mcap", LAYOUT) as log:
        with pytest.raises(LogWriteError, match=r"sample\.x_ref: expected 2 values, got 3"):
            log.sample(**{**GOOD, "x_ref": (1.0, 2.0, 3.0)})
        with pytest.raises(LogWriteError, match=r"sample\.seq"):
            log.sample(**{**GOOD, "seq": -1})
        with pytest.raises(LogWriteError, match=r"sample\.flags"):
            log.sample(**{**GOOD, "flags": 256})
        with pytest.raises(LogWriteError, match=r"truth\.state: expected 2 values, got 1"):
            log.truth(0, (1.0,), (0.0,), (0.0,), 0, 1)
        with pytest.raises(LogWriteError, match="event level"):
            log.event(0, "fatal", "x", "y")
        with pytest.raises(LogWriteError, match="at most 64"):
            log.frame_raw(0, 1, True, 65, bytes(65), 0)
        log.sample(**GOOD)
    data = read_log(tmp_path / "x.mcap")
    assert len(data.samples) == 1  # the rejected records left nothing behind
    assert issubclass(LogWriteError, DobHilError)


def test_close_twice_and_exception_summary(tmp_path: Path) -> None:
    path = tmp_path / "exc.mcap"
    with pytest.raises(RuntimeError, match="boom"), LogWriter(path, LAYOUT) as log:
        log.sample(**GOOD)
        raise RuntimeError("boom")
    log.close()  # second close: nothing happens
    data = read_log(path)
    assert data.metadata["summary"]["exit_reason"] == "exception: RuntimeError: boom"
    assert len(data.samples) == 1 and data.warnings == []


def test_full_backlog_drops_whole_batches_counted_and_reported(tmp_path: Path) -> None:
    """Stop the writer process; the pipe (1 MiB) and a 64 KiB backlog fill; then records drop."""
    path = tmp_path / "overflow.mcap"
    run = SyntheticRun(LAYOUT)
    log = LogWriter(path, LAYOUT, max_backlog_bytes=64 * 1024, backpressure=False)
    assert log._proc is not None
    pid = log._proc.pid
    os.kill(pid, signal.SIGSTOP)
    try:
        k = 0
        while log.stats.dropped_records < 500:
            run.period(log, k)
            log.flush()
            k += 1
            assert k < 200_000, "the backlog never filled"
        assert log.stats.backlog_high_water_bytes <= 64 * 1024
    finally:
        os.kill(pid, signal.SIGCONT)
    for _ in range(20):  # after the writer resumes, the next batch carries the overflow event
        run.period(log, k)
        k += 1
    log.flush(force=True)
    stats_before_close = log.stats
    log.close({"exit_reason": "test"})
    data = read_log(path)
    overflow = [e for e in data.events if e["kind"] == "log_overflow"]
    assert len(overflow) == 1 and overflow[0]["level"] == "warning"
    assert overflow[0]["data"]["dropped_records"] == stats_before_close.dropped_records
    assert data.metadata["summary"]["dropped_records"] == str(log.stats.dropped_records)
    written = log.stats.written_records
    assert written is not None
    total_written = sum(v for key, v in written.items() if key.endswith("_written"))
    assert (
        total_written + log.stats.dropped_records
        == 4 * k + len([e for e in data.events if e["kind"] == "progress"]) + 1
    )
    # the samples that survived are whole, in order, with a gap where batches were dropped
    seq = data.samples["seq"].astype(int)
    assert (seq[1:] > seq[:-1]).all() and seq[-1] == k - 1
    assert len(seq) == written["samples_written"]


def test_writer_failure_mid_run_surfaces_in_flush_and_close(tmp_path: Path) -> None:
    """The writer process hits the file size limit (like a full disk); flush() then raises."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (256 * 1024, hard))
    try:
        log = LogWriter(tmp_path / "full.mcap", LAYOUT, chunk_size_bytes=4096)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    run = SyntheticRun(LAYOUT)
    error: LogWriteError | None = None
    for k in range(100_000):
        run.period(log, k)
        try:
            log.flush(force=True)
        except LogWriteError as exc:
            error = exc
            break
    assert error is not None and "File too large" in str(error)
    assert "records so far lost (the file holds" in str(error)  # how much was lost
    with pytest.raises(LogWriteError, match="File too large"):
        log.flush()
    with pytest.raises(LogWriteError, match="File too large"):
        log.close()
    log.close()  # and a second close does nothing


def test_flush_is_lazy_until_due(tmp_path: Path) -> None:
    with LogWriter(tmp_path / "lazy.mcap", LAYOUT, flush_interval_ns=10**12, flush_bytes=1 << 20) as log:
        log.sample(**GOOD)
        log.flush()
        assert log.stats.enqueued_records == 0  # not due: still in the local batch
        log.flush(force=True)
        assert log.stats.enqueued_records == 1
    data: Any = read_log(tmp_path / "lazy.mcap")
    assert len(data.samples) == 1


def test_backpressure_waits_for_a_stalled_writer_and_fails_after_the_stall_timeout(tmp_path: Path) -> None:
    """Under backpressure nothing is dropped: a writer that takes nothing ends the run instead."""
    log = LogWriter(tmp_path / "stall.mcap", LAYOUT, max_backlog_bytes=64 * 1024, stall_timeout_s=0.5)
    assert log._proc is not None
    pid = log._proc.pid
    run = SyntheticRun(LAYOUT)
    os.kill(pid, signal.SIGSTOP)
    try:
        with pytest.raises(LogWriteError, match=r"took nothing for 0\.5 s"):
            for k in range(200_000):
                run.period(log, k)
                log.flush()
        assert log.stats.dropped_records > 0  # the batch that could not be handed over
        assert log.stats.backpressure_wait_ns >= 0.5e9
    finally:
        os.kill(pid, signal.SIGCONT)
    with pytest.raises(LogWriteError):
        log.close()


@pytest.fixture
def cpu_hogs() -> Any:
    """Two busy processes beside the test, as on a loaded machine."""
    import subprocess
    import sys

    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    try:
        yield hogs
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()


def test_backpressure_loses_nothing_beside_cpu_hogs(tmp_path: Path, cpu_hogs: Any) -> None:
    """A loop far faster than the writer, a tiny backlog, two CPU hogs: every record arrives."""
    path = tmp_path / "bp.mcap"
    n = 60_000
    run = SyntheticRun(LAYOUT)
    with LogWriter(path, LAYOUT, max_backlog_bytes=16 * 1024, backpressure=True) as log:
        for k in range(n):
            run.period(log, k)
            log.flush()
    assert log.stats.dropped_records == 0
    report = assert_complete(path)
    assert report["/dob_hil/sample"].messages == n and report["/dob_hil/truth"].messages == n
    data = read_log(path)
    assert data.complete and data.metadata["summary"]["dropped_records"] == "0"
    assert int(data.metadata["summary"]["log_backpressure_wait_ns"]) == log.stats.backpressure_wait_ns


def test_records_from_another_thread_are_neither_lost_nor_duplicated(tmp_path: Path) -> None:
    """The embedded real-time drive writes truth from its timer thread while the loop writes samples."""
    import threading

    path = tmp_path / "threads.mcap"
    n = 40_000
    with LogWriter(path, LAYOUT, flush_bytes=4096) as log:
        stop = threading.Event()

        def drive() -> None:
            for k in range(n):
                log.truth(k * 1000, (0.1, 0.2), (0.0,), (0.5,), k, 1)
                if k % 500 == 0:
                    log.event(k * 1000, "info", "drive", "from the timer thread")
            stop.set()

        thread = threading.Thread(target=drive)
        thread.start()
        k = 0
        while not stop.is_set() or k < 1000:
            log.sample(**{**GOOD, "time_ns": k * 1000, "seq": k})
            log.frame_raw(k * 1000, 0x181, True, 2, b"\x01\x02", 0)
            log.flush(force=k % 7 == 0)
            k += 1
        thread.join()
    report = assert_complete(path)
    assert report["/dob_hil/truth"].messages == n and report["/dob_hil/sample"].messages == k
    truth = read_log(path).truth
    assert np.array_equal(truth["period_index"], np.arange(n))


def test_the_checker_finds_dropped_and_duplicated_records(tmp_path: Path) -> None:
    """Records dropped under real-time policy show as missing sequence numbers."""
    path = tmp_path / "drops.mcap"
    run = SyntheticRun(LAYOUT)
    log = LogWriter(path, LAYOUT, max_backlog_bytes=16 * 1024, backpressure=False)
    assert log._proc is not None
    os.kill(log._proc.pid, signal.SIGSTOP)
    try:
        k = 0
        while log.stats.dropped_records < 100:
            run.period(log, k)
            log.flush()
            k += 1
    finally:
        os.kill(log._proc.pid, signal.SIGCONT)
    for j in range(k, k + 20):  # records after the drops: the drops become a gap
        run.period(log, j)
    log.flush(force=True)
    log.close()
    report = check_sequences(path)
    assert report["/dob_hil/sample"].missing > 0 and report["/dob_hil/sample"].duplicates == 0
    with pytest.raises(AssertionError, match="missing"):
        assert_complete(path)


def test_dev_null_runs_without_a_writer_process_and_closes(tmp_path: Path) -> None:
    log = LogWriter(Path(os.devnull), LAYOUT)
    assert log._proc is None
    for k in range(100):
        log.sample(**{**GOOD, "seq": k})
        log.flush()
    log.close({"exit_reason": "done"})
    assert log.stats.enqueued_records == 100 and log.stats.dropped_records == 0


def test_clocked_frame_hook_writes_what_frame_raw_writes(tmp_path: Path) -> None:
    """The lockstep frame hook (records built in place) and frame_raw give the same frames."""

    msgs = [
        (can.Message(arbitration_id=0x181, data=bytes([1, 2, 3, 4, 5, 6]), is_extended_id=False), True),
        (can.Message(arbitration_id=0x201, data=b"\x10\x00\x85", is_extended_id=False), False),
        (can.Message(arbitration_id=0x1ABCDEF, data=b"\x01", is_extended_id=True), True),  # general path
        (can.Message(arbitration_id=0x7FF, is_remote_frame=True, dlc=8, is_extended_id=False), False),
        (can.Message(arbitration_id=0x123, data=bytes(range(12)), is_fd=True, is_extended_id=False), True),
        (can.Message(arbitration_id=0x0, data=b"", is_extended_id=False), True),
    ]
    times = iter(range(1000, 100_000, 300))
    clock_ns = lambda: next(times)  # noqa: E731
    with LogWriter(tmp_path / "hook.mcap", LAYOUT) as log:
        hook = log.clocked_frame_hook(CallClock(clock_ns))
        for _ in range(3):
            for msg, is_rx in msgs:
                hook(msg, is_rx)
    times = iter(range(1000, 100_000, 300))
    with LogWriter(tmp_path / "raw.mcap", LAYOUT) as log:
        for _ in range(3):
            for msg, is_rx in msgs:
                flags = (CAN_FLAG_EXTENDED if msg.is_extended_id else 0) | (CAN_FLAG_FD if msg.is_fd else 0)
                flags |= CAN_FLAG_REMOTE if msg.is_remote_frame else 0
                log.frame_raw(clock_ns(), msg.arbitration_id, is_rx, msg.dlc, msg.data or b"", flags)
    a, b = read_log(tmp_path / "hook.mcap"), read_log(tmp_path / "raw.mcap")
    assert len(a.frames) == 15 and len(a.fd_frames) == 3
    for name in a.frames.dtype.names or ():
        assert np.array_equal(a.frames[name], b.frames[name]), name
    for name in a.fd_frames.dtype.names or ():
        assert np.array_equal(a.fd_frames[name], b.fd_frames[name]), name


def test_clocked_frame_hook_logs_each_frame_at_the_sources_time_then(tmp_path: Path) -> None:
    """The lockstep stamper's hook reads ``source.time_ns`` when the frame passes, not when packed."""

    class Source:
        time_ns = 0

    source = Source()
    msgs = [can.Message(arbitration_id=0x80 + i, data=bytes([i]), is_extended_id=False) for i in range(5)]
    path = tmp_path / "source.mcap"
    with LogWriter(path, LAYOUT) as log:
        hook = log.clocked_frame_hook(source)
        for i, msg in enumerate(msgs):
            source.time_ns = 1000 * i
            hook(msg, i % 2 == 0)
        source.time_ns = 10**9  # packed later: the times taken when staged count
    frames = read_log(path).frames
    assert list(frames["timestamp_ns"]) == [0, 1000, 2000, 3000, 4000]
    assert list(frames["arbitration_id"]) == [0x80, 0x81, 0x82, 0x83, 0x84]
    assert list(frames["direction"]) == [CAN_RX, CAN_TX, CAN_RX, CAN_TX, CAN_RX]
