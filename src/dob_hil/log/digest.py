"""A digest of every record of a log, to show that two runs (or two versions of the code) wrote
the same records: samples without ``compute_ns`` (a wall-clock figure), frames, FD frames, ground
truth and events without wall-clock fields. ``tools/log_digest.py`` prints it for the shipped
scenarios; the fast-path tests compare it between a fast and a general run."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dob_hil.log.reader import read_log


@dataclass(frozen=True)
class LogDigest:
    samples: int
    frames: int
    truth: int
    events: int
    sha256: str

    def __str__(self) -> str:
        counts = f"samples={self.samples} frames={self.frames} truth={self.truth} events={self.events}"
        return f"{counts} {self.sha256[:16]}"


def log_digest(path: Path | str) -> LogDigest:
    data = read_log(path)
    h = hashlib.sha256()
    s = data.samples
    for name in s.dtype.names or ():
        if name != "compute_ns":
            h.update(np.ascontiguousarray(s[name]).tobytes())
    for records in (data.frames, data.fd_frames, data.truth):
        h.update(np.ascontiguousarray(records).tobytes())
    for event in data.events:
        h.update(repr(sorted((k, v) for k, v in event.items() if k != "wall_time_ns")).encode())
    return LogDigest(len(s), len(data.frames), len(data.truth), len(data.events), h.hexdigest())
