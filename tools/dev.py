#!/usr/bin/env python3
"""One entry point for a fresh clone: creates .venv, installs the project, runs the demo or the tests.

    python3 tools/dev.py demo    # the paper's example end to end on the simulated drive
    python3 tools/dev.py test    # ruff, mypy and the whole pytest suite

Only the standard library is used here, so it runs with nothing but python3.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
VENV = ROOT / ".venv"
STAMP = VENV / ".dob-hil-installed"
BIN = VENV / ("Scripts" if os.name == "nt" else "bin")


def _python() -> str:
    return str(BIN / "python")


def _ensure_env() -> None:
    digest = hashlib.sha256((ROOT / "pyproject.toml").read_bytes()).hexdigest()
    if STAMP.exists() and STAMP.read_text() == digest:
        return
    if not (BIN / "python").exists():
        print(f"dev: creating {VENV}", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
    print("dev: installing dob-hil and its dependencies into .venv", flush=True)
    subprocess.run(
        [_python(), "-m", "pip", "install", "--quiet", "--disable-pip-version-check", "-e", f"{ROOT}[dev]"],
        check=True,
        cwd=ROOT,
    )
    STAMP.write_text(digest)


def _run(cmd: list[str]) -> int:
    print("dev: $ " + " ".join(cmd), flush=True)
    return subprocess.run(cmd, check=False, cwd=ROOT).returncode


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in {"demo", "test", "env"}:
        print(__doc__, file=sys.stderr)
        return 2
    _ensure_env()
    what, rest = argv[0], argv[1:]
    if what == "env":
        return 0
    if what == "demo":
        return _run([str(BIN / "dob-hil"), "demo", *rest])
    for cmd in (
        [_python(), "-m", "ruff", "check", "src", "firmware_sim", "tests", "benchmarks", "tools"],
        [_python(), "-m", "mypy"],
        [_python(), "-m", "pytest", "-n", "2", "-q", *rest],
    ):
        rc = _run(cmd)
        if rc != 0:
            return rc
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
