"""log_digest's parts: the whole digest is unchanged by them, and they name the part that moved."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import pytest

from dob_hil.log.digest import log_digest
from dob_hil.log.writer import LogWriter


def test_parts_name_the_truth_state_alone_when_only_it_moved(
    tmp_path: Path, run_writer: Callable[..., Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    run_writer(tmp_path / "a.mcap", 300)
    run_writer(tmp_path / "b.mcap", 300)
    a, b = log_digest(tmp_path / "a.mcap"), log_digest(tmp_path / "b.mcap")
    assert a == b
    names = [name for name, _ in a.parts]
    assert names == ["samples", "frames", "fd_frames", "truth_state", "truth_rest", "events"]

    original = LogWriter.truth

    def nudged(self: LogWriter, time_ns: int, state: Sequence[float], *rest: Any, **kw: Any) -> None:
        original(self, time_ns, [math.nextafter(v, math.inf) for v in state], *rest, **kw)

    monkeypatch.setattr(LogWriter, "truth", nudged)
    run_writer(tmp_path / "c.mcap", 300)
    c = log_digest(tmp_path / "c.mcap")
    assert c.sha256 != a.sha256
    moved = [name for (name, x), (_, y) in zip(a.parts, c.parts, strict=True) if x != y]
    assert moved == ["truth_state"]
    assert c.parts_text().count("=") == len(a.parts)
