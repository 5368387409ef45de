"""Every ``benchmarks/bench_*.py`` runs to completion with ``--smoke``.

Only the exit status and that a report was printed are checked: the figures are wall-clock
measurements of a shared machine, never asserted here. A benchmark that cannot run on this
machine (no udp_multicast) exits with status 77 and its test is skipped with the reason printed.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

BENCH_DIR = Path(__file__).resolve().parents[1] / "benchmarks"
SCRIPTS = sorted(BENCH_DIR.glob("bench_*.py"))
SKIP_STATUS = 77
REALTIME = {"bench_realtime.py", "bench_soak.py", "bench_live.py"}


def _params() -> list[object]:
    out: list[object] = []
    for script in SCRIPTS:
        marks = [pytest.mark.realtime] if script.name in REALTIME else []
        out.append(pytest.param(script, id=script.stem, marks=marks))
    return out


def test_every_benchmark_is_found() -> None:
    names = {s.name for s in SCRIPTS}
    expected = {"bench_step.py", "bench_lockstep.py", "bench_realtime.py", "bench_logging.py",
                "bench_analysis.py", "bench_cli.py", "bench_soak.py", "bench_campaign.py"}  # fmt: skip
    assert expected <= names, sorted(expected - names)


@pytest.mark.parametrize("script", _params())
def test_benchmark_smoke(script: Path, tmp_path: Path) -> None:
    env = dict(os.environ)
    env["TMPDIR"] = str(tmp_path)  # scratch logs and caches land in the test's own folder
    proc = subprocess.run(
        [sys.executable, script.name, "--smoke"],
        cwd=BENCH_DIR,
        env=env,
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
    )
    if proc.returncode == SKIP_STATUS:
        pytest.skip(proc.stdout.strip() or f"{script.name} cannot run here")
    assert proc.returncode == 0, f"{script.name} --smoke: exit {proc.returncode}\n{proc.stderr[-3000:]}"
    assert proc.stdout.strip(), f"{script.name} --smoke printed nothing\n{proc.stderr[-3000:]}"
    assert proc.stdout.startswith("== "), proc.stdout[:500]
