"""Whole runs and their logs: lockstep beside CPU hogs loses nothing; ``--no-log`` and
``--log /dev/null`` run to the end and print the summary."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from dob_hil.log import read_log
from dob_hil.log.check import assert_complete

CLI = [sys.executable, "-m", "dob_hil.cli"]


@pytest.fixture
def cpu_hogs() -> Iterator[list[subprocess.Popen[bytes]]]:
    """Two busy processes beside the run, as on a loaded machine."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    try:
        yield hogs
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    command = [*CLI, "run", "--no-progress", *args]
    return subprocess.run(command, check=False, capture_output=True, text=True, timeout=600)


def test_long_lockstep_run_beside_cpu_hogs_has_every_record(
    tmp_path: Path, cpu_hogs: list[subprocess.Popen[bytes]]
) -> None:
    """The loop waits for the writer (backpressure) instead of dropping: every sequence number of
    every channel is in the log, and analyze-level reading says complete."""
    path = tmp_path / "long.mcap"
    done = _run("--scenario", "paper-sine", "--duration", "30", "--log", str(path), "--json")
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["log_dropped_records"] == 0
    report = assert_complete(path)
    assert report["/dob_hil/sample"].messages == summary["samples"] == 100_000
    assert report["/dob_hil/truth"].messages >= summary["samples"]
    data = read_log(path, topics=["/dob_hil/event"])
    assert data.complete and data.metadata["summary"]["dropped_records"] == "0"
    assert int(data.metadata["summary"]["log_backpressure_wait_ns"]) >= 0


@pytest.mark.parametrize("log_args", [["--no-log"], ["--log", os.devnull]])
def test_runs_without_a_log_file_print_the_summary(log_args: list[str]) -> None:
    done = _run("--scenario", "paper-step", "--duration", "0.5", *log_args)
    assert done.returncode == 0, done.stderr
    assert "run paper-step: completed" in done.stdout and os.devnull in done.stdout


def test_no_log_and_log_together_are_refused(tmp_path: Path) -> None:
    done = _run(
        "--scenario", "paper-step", "--duration", "0.5", "--no-log", "--log", str(tmp_path / "x.mcap")
    )
    assert done.returncode == 2 and "--no-log" in done.stderr and "Traceback" not in done.stderr
