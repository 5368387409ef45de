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
    # a SHA-256 per part, in the order of the whole digest: samples, frames, fd_frames, the
    # truth's plant state, the rest of the truth, events (which part a change moved)
    parts: tuple[tuple[str, str], ...] = ()

    def __str__(self) -> str:
        counts = f"samples={self.samples} frames={self.frames} truth={self.truth} events={self.events}"
        return f"{counts} {self.sha256[:16]}"

    def parts_text(self) -> str:
        """One short digest per part: ``samples=... frames=... truth_state=...``."""
        return " ".join(f"{name}={digest[:10]}" for name, digest in self.parts)


def log_digest(path: Path | str) -> LogDigest:
    data = read_log(path)
    whole = hashlib.sha256()
    parts: list[tuple[str, str]] = []

    def part(name: str, chunks: list[bytes]) -> None:
        h = hashlib.sha256()
        for chunk in chunks:
            whole.update(chunk)
            h.update(chunk)
        parts.append((name, h.hexdigest()))

    s = data.samples
    part("samples", [np.ascontiguousarray(s[n]).tobytes() for n in s.dtype.names or () if n != "compute_ns"])
    part("frames", [np.ascontiguousarray(data.frames).tobytes()])
    part("fd_frames", [np.ascontiguousarray(data.fd_frames).tobytes()])
    truth = data.truth
    # the whole digest takes the truth records as they are; the parts split the plant state off
    # (a change of integration order moves it by rounding only)
    whole.update(np.ascontiguousarray(truth).tobytes())
    state = hashlib.sha256(np.ascontiguousarray(truth["state"]).tobytes()).hexdigest()
    rest = hashlib.sha256()
    for n in truth.dtype.names or ():
        if n != "state":
            rest.update(np.ascontiguousarray(truth[n]).tobytes())
    parts += [("truth_state", state), ("truth_rest", rest.hexdigest())]
    part(
        "events",
        [repr(sorted((k, v) for k, v in e.items() if k != "wall_time_ns")).encode() for e in data.events],
    )
    return LogDigest(
        len(s), len(data.frames), len(data.truth), len(data.events), whole.hexdigest(), tuple(parts)
    )
