#!/usr/bin/env python3
"""Digests of lockstep logs of the shipped scenarios, to show a change keeps every record.

Runs each shipped scenario (and noise + loss variants of the step scenarios) for 1.5 s in
lockstep and prints one line per case: the record counts and a SHA-256 over every channel's
records (samples without ``compute_ns``, a wall-clock figure; frames; FD frames; truth; events
without wall-clock fields). Run it before and after a change and compare the outputs:

    .venv/bin/python tools/log_digest.py > before.txt   # on the old code
    .venv/bin/python tools/log_digest.py > after.txt    # on the new code
    diff before.txt after.txt

``--log-layout blocks`` writes the logs in the block layout: the digests are those of the default
layout (the same records, read back alike). ``--parts`` adds a digest per part (samples, frames,
FD frames, the truth's plant state, the rest of the truth, events), to show which part a change
moved: a new integration order, for one, moves the plant state by rounding and nothing else.
"""

from __future__ import annotations

import dataclasses
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

from dob_hil.config import Config, load_config
from dob_hil.log.digest import log_digest
from dob_hil.loop.session import RunOptions, run_session
from dob_hil.scenarios import scenario_path

SCENARIOS = (
    "paper-step", "paper-sine", "paper-step-cia402", "paper-sine-cia402", "paper-step-odrive",
    "paper-step-optimized", "mimo-2x2",
)  # fmt: skip
IMPAIRED = ("paper-step", "paper-step-cia402", "paper-step-odrive", "mimo-2x2")
DURATION_S = 1.5


def cases(name: str) -> Iterator[tuple[str, Config]]:
    config = load_config(scenario_path(name))
    yield name, config
    if name in IMPAIRED:
        sim = dataclasses.replace(config.sim, noise_counts_std=2.0, loss_probability=0.02, seed=7)
        yield f"{name}+noise+loss", dataclasses.replace(config, sim=sim)


def main(argv: list[str]) -> int:
    layout = "samples"
    if "--log-layout" in argv:
        i = argv.index("--log-layout")
        layout = argv[i + 1] if i + 1 < len(argv) else ""
        argv = argv[:i] + argv[i + 2 :]
        if layout not in ("samples", "blocks"):
            print(f"log_digest: --log-layout: expected samples or blocks, got {layout!r}", file=sys.stderr)
            return 2
    parts = "--parts" in argv
    argv = [a for a in argv if a != "--parts"]
    only = set(argv)
    with tempfile.TemporaryDirectory(prefix="log-digest-") as tmp:
        for scenario in SCENARIOS:
            if only and scenario not in only:
                continue
            for label, config in cases(scenario):
                path = Path(tmp) / f"{label}.mcap"
                run_session(config, RunOptions(duration_s=DURATION_S, log_path=path, log_layout=layout))
                digest = log_digest(path)
                extra = f" {digest.parts_text()}" if parts else ""
                print(f"{label:32s} {digest}{extra}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
