"""Helpers of the analysis tests: real runs on the embedded simulated drive, and log rewriting."""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import numpy as np

from dob_hil.config import parse_config_text
from dob_hil.log import LogData, LogWriter, read_log
from dob_hil.loop.session import RunOptions, run_session
from dob_hil.scenarios import scenario_path


def scenario_text(name: str, **replace: str) -> str:
    """A shipped scenario's TOML text with lines edited: ``{old_line_start: new_text}``."""
    text = scenario_path(name).read_text(encoding="utf-8")
    for old, new in replace.items():
        assert old in text, old
        text = text.replace(old, new, 1)
    return text


def run_log(path: Path, text: str, *, dob: bool, duration_s: float) -> Path:
    """One lockstep run of the config ``text`` on the embedded simulated drive, logged to ``path``."""
    config = parse_config_text(text)
    summary = run_session(config, RunOptions(dob_enabled=dob, duration_s=duration_s, log_path=path))
    assert summary.exit_reason == "completed", summary.exit_reason
    return path


def _rows(array: np.ndarray) -> list[tuple[Any, ...]]:
    assert array.dtype.names is not None
    columns = [array[name].tolist() for name in array.dtype.names]
    return list(zip(*columns, strict=True))


def rewrite_log(
    data: LogData,
    path: Path,
    *,
    samples: np.ndarray | None = None,
    truth: np.ndarray | None = None,
    events: list[dict[str, Any]] | None = None,
    attachments: dict[str, bytes] | None = None,
    run: dict[str, str] | None = None,
    frames: bool = True,
) -> Path:
    """Write ``data`` again (optionally with other samples, truth, events, attachments, run record)."""
    samples = data.samples if samples is None else samples
    truth = data.truth if truth is None else truth
    metadata = {"run": data.metadata.get("run", {}) if run is None else run}
    with LogWriter(
        path,
        data.layout,
        metadata=metadata,
        attachments=data.attachments if attachments is None else attachments,
    ) as log:
        for row in _rows(samples):
            log.sample(*row)
        if frames:
            for ts, aid, direction, dlc, flags, payload in _rows(data.frames):
                length = 0 if flags & 0x04 else min(dlc, 8)
                log.frame_raw(ts, aid, direction == 0, dlc, bytes(payload[:length]), flags)
        for row in _rows(truth):
            log.truth(*row)
        for ev in data.events if events is None else events:
            log.event(ev["time_ns"], ev["level"], ev["kind"], ev["message"], ev.get("data"))
        log.flush(force=True)
    return path


def reread(path: Path) -> LogData:
    return read_log(path)


EditFn = Callable[[np.ndarray], None]


class Receiver(threading.Thread):
    """Collects frames from a virtual channel until ``expected`` arrived or 10 s passed quiet (the
    receiving end of ``replay --to-bus`` tests)."""

    def __init__(self, channel: str, expected: int) -> None:
        super().__init__(daemon=True)
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.expected = expected
        self.got: list[can.Message] = []

    def run(self) -> None:
        try:
            while len(self.got) < self.expected:
                msg = self.bus.recv(10.0)
                if msg is None:
                    return
                self.got.append(msg)
        finally:
            self.bus.shutdown()
