"""LogWriter: errors that name what is wrong, bounded backlog with counted drops, failures surface."""

from __future__ import annotations

import os
import resource
import signal
from pathlib import Path
from typing import Any

import pytest

from dob_hil.errors import DobHilError
from dob_hil.log import LogLayout, LogWriteError, LogWriter, read_log
from dob_hil.log.bench import SyntheticRun

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
    log = LogWriter(path, LAYOUT, max_backlog_bytes=64 * 1024)
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
