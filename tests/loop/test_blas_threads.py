"""BLAS runs on one thread while a session runs (dob_hil.loop.blas): no spinning workers beside
the loop, in the log writer process too; the heap is frozen while the loop runs
(dob_hil.loop.heap). Checked from inside the loop (the progress callback runs on the loop's thread)."""

from __future__ import annotations

import gc
import os
from pathlib import Path

import pytest
from threadpoolctl import threadpool_info, threadpool_limits

import firmware_sim.cli
from dob_hil.config import Config
from dob_hil.log import LogLayout, LogWriter
from dob_hil.loop.blas import one_blas_thread
from dob_hil.loop.heap import frozen_heap
from dob_hil.loop.session import RunOptions, run_session


def _blas_threads() -> dict[str, int]:
    return {lib["filepath"]: lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"}


def test_every_blas_is_limited_inside_and_restored_after(paper_step: Config, log_path: Path) -> None:
    seen: list[dict[str, int]] = []
    with threadpool_limits(limits=2, user_api="blas"):
        before = _blas_threads()
        run_session(
            paper_step,
            RunOptions(log_path=log_path, duration_s=0.1, progress=lambda k, n: seen.append(_blas_threads())),
        )
        after = _blas_threads()
    assert seen, "the loop reported no progress"
    # numpy's and scipy's own OpenBLAS (the limit must reach the one scipy.linalg loads)
    assert len(seen[0]) >= 2, seen[0]
    assert all(n == 1 for threads in seen for n in threads.values()), seen
    assert after == before


def test_the_limit_covers_libraries_loaded_by_scipy_linalg() -> None:
    with one_blas_thread():
        import scipy.linalg  # noqa: F401  (already loaded by dob_hil.loop.blas)

        threads = _blas_threads()
    assert any("scipy" in path for path in threads), threads
    assert set(threads.values()) == {1}


def test_the_drive_process_runs_with_one_blas_thread(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[dict[str, int]] = []

    def fake_main(argv: object) -> int:
        seen.append(_blas_threads())
        return 0

    monkeypatch.setattr(firmware_sim.cli, "_main", fake_main)
    with threadpool_limits(limits=2, user_api="blas"):
        before = _blas_threads()
        assert firmware_sim.cli.main([]) == 0
        assert _blas_threads() == before
    assert seen and set(seen[0].values()) == {1}


def test_the_log_writer_process_runs_one_thread(tmp_path: Path) -> None:
    """The writer process imports numpy: without the limit its OpenBLAS starts a worker per CPU,
    which spin beside the control loop as a run starts. Once it is ready it runs one thread."""
    log = LogWriter(tmp_path / "one.mcap", LogLayout(2, 1, 1, 2))
    try:
        assert log._proc is not None
        pid = log._proc.pid
        assert "numpy" in Path(f"/proc/{pid}/maps").read_text()  # its imports are done
        assert len(os.listdir(f"/proc/{pid}/task")) == 1
        environ = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
        assert b"OPENBLAS_NUM_THREADS=1" in environ
    finally:
        log.close({"exit_reason": "done"})


def test_the_heap_is_frozen_while_the_loop_runs_and_returned_after(
    paper_step: Config, log_path: Path
) -> None:
    """dob_hil.loop.heap: the setup's objects in the permanent generation during the loop only."""
    frozen: list[int] = []
    before = gc.get_freeze_count()
    run_session(
        paper_step,
        RunOptions(
            log_path=log_path, duration_s=0.1, progress=lambda k, n: frozen.append(gc.get_freeze_count())
        ),
    )
    assert frozen and min(frozen) > 10_000  # the modules, the design, the drive: frozen
    assert gc.get_freeze_count() == before
    assert gc.isenabled()


def test_frozen_heap_returns_the_objects_when_the_loop_fails() -> None:
    with pytest.raises(RuntimeError), frozen_heap():
        assert gc.get_freeze_count() > 0
        raise RuntimeError("the loop failed")
    assert gc.get_freeze_count() == 0


def test_frozen_heap_leaves_an_earlier_freeze_alone() -> None:
    gc.freeze()
    try:
        before = gc.get_freeze_count()
        with frozen_heap(), frozen_heap():
            assert gc.get_freeze_count() >= before
        assert gc.get_freeze_count() == before  # the application's freeze is still there
    finally:
        gc.unfreeze()
