"""A log with dropped records is reported incomplete by analyze, with the count."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pytest

from dob_hil.cli import main
from dob_hil.log import LogWriter, read_log
from dob_hil.log.bench import PAPER_LAYOUT, SyntheticRun
from dob_hil.log.check import check_sequences


def test_dropped_records_make_the_log_incomplete(tmp_path: Path, runs: dict[tuple[str, bool], Path],
                                                 capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    base = read_log(runs[("paper-step", True)])
    path = tmp_path / "dropped.mcap"
    run = SyntheticRun(PAPER_LAYOUT)
    log = LogWriter(path, PAPER_LAYOUT, metadata={"run": base.metadata["run"]}, attachments=base.attachments,
                    max_backlog_bytes=16 * 1024, backpressure=False)  # fmt: skip
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
    deadline = time.monotonic() + 120
    while log.stats.backlog_bytes and time.monotonic() < deadline:  # the writer catches up
        log.flush(force=True)
        time.sleep(0.01)
    for j in range(k, k + 50):
        run.period(log, j)
    log.flush(force=True)
    log.close()
    dropped = log.stats.dropped_records
    assert check_sequences(path)["/dob_hil/sample"].missing > 0
    assert main(["analyze", str(path), "--no-plots", "--json"]) == 0
    captured = capsys.readouterr()
    metrics = json.loads(captured.out)[0]
    assert metrics["complete"] is False and metrics["log_dropped_records"] == dropped
    assert f"{dropped} log records were dropped" in captured.err
