"""Fixtures of the log tests: a deterministic synthetic run, recorded call by call."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from dob_hil.log import LogLayout, LogWriter, run_metadata
from dob_hil.log.bench import PAPER_LAYOUT, PERIOD_NS, SyntheticRun


class Recorder:
    """Stands in for LogWriter in SyntheticRun and records every call, to compare with the file."""

    def __init__(self) -> None:
        self.samples: list[tuple[Any, ...]] = []
        self.frames: list[tuple[Any, ...]] = []
        self.truth_rows: list[tuple[Any, ...]] = []
        self.events: list[dict[str, Any]] = []

    def sample(self, *args: Any) -> None:
        self.samples.append(args)

    def frame_raw(self, *args: Any) -> None:
        self.frames.append(args)

    def truth(self, *args: Any) -> None:
        self.truth_rows.append(args)

    def event(self, time_ns: int, level: str, kind: str, message: str, data: Any = None) -> None:
        self.events.append(
            {"time_ns": time_ns, "level": level, "kind": kind, "message": message, "data": data or {}}
        )

    def flush(self, force: bool = False) -> None:
        pass


class Tee:
    """Calls both a LogWriter and a Recorder."""

    def __init__(self, log: LogWriter, rec: Recorder) -> None:
        self.log, self.rec = log, rec

    def __getattr__(self, name: str) -> Callable[..., None]:
        def call(*args: Any, **kwargs: Any) -> None:
            getattr(self.rec, name)(*args, **kwargs)
            getattr(self.log, name)(*args, **kwargs)

        return call


def write_run(
    path: Path,
    n: int,
    layout: LogLayout = PAPER_LAYOUT,
    extra: Callable[[Tee, int], None] | None = None,
    **options: Any,
) -> tuple[Recorder, LogWriter]:
    """Write ``n`` synthetic periods (sample, 2 frames, truth) and record what was written."""
    rec = Recorder()
    run = SyntheticRun(layout)
    meta = {"run": run_metadata(mode="lockstep", bus="virtual", period_ns=PERIOD_NS, layout=layout)}
    attachments = {"design.json": b'{"Kc": [[1.0, 2.0]]}', "config.toml": "[plant]\nname = 'ü'\n".encode()}
    with LogWriter(path, layout, metadata=meta, attachments=attachments, **options) as log:
        tee = Tee(log, rec)
        for k in range(n):
            run.period(tee, k)  # type: ignore[arg-type]
            if extra is not None:
                extra(tee, k)
            log.flush()
    return rec, log


@pytest.fixture(scope="session")
def small_log(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Recorder, LogWriter]:
    """2000 periods in small (4 KiB) chunks, so that damage tests have many chunks to hit."""
    path = tmp_path_factory.mktemp("log") / "small.mcap"
    rec, log = write_run(path, 2000, chunk_size_bytes=4096)
    return path, rec, log


@pytest.fixture
def run_writer() -> Callable[..., tuple[Recorder, LogWriter]]:
    """The :func:`write_run` helper, as a fixture (test modules do not import conftest)."""
    return write_run


@pytest.fixture(scope="session")
def session_run_writer() -> Callable[..., tuple[Recorder, LogWriter]]:
    """:func:`write_run` for module- and session-scoped fixtures."""
    return write_run
