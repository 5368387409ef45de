"""Start ``python -m firmware_sim`` as its own process on a bus, for real-time tests."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import can
import pytest

from dob_hil.scenarios import scenario_path

REPO_ROOT = Path(__file__).resolve().parents[2]


def udp_channel_or_skip() -> str:
    channel = f"239.74.163.{random.randint(10, 250)}"
    try:
        can.Bus(interface="udp_multicast", channel=channel).shutdown()
    except (OSError, can.CanError, ImportError, NotImplementedError, ValueError) as exc:
        pytest.skip(f"udp_multicast cannot be opened here: {exc}")
    return channel


def paper_config_for_node(tmp_path: Path, node_id: int, *, patience_periods: int = 200) -> Path:
    """paper-step with its own node id (tests share the multicast port) and patient timeouts.

    The timeouts are widened from 10 periods (3 ms) so that a VM stall of a loaded CI machine
    (measured 2-36 ms on this kind of machine) does not end a test run.
    """
    text = scenario_path("paper-step").read_text()
    text = text.replace("node_id = 1\n", f"node_id = {node_id}\n")
    text = text.replace("watchdog_periods = 10\n", f"watchdog_periods = {patience_periods}\n")
    text = text.replace("feedback_timeout_periods = 10\n", f"feedback_timeout_periods = {patience_periods}\n")
    path = tmp_path / f"paper-node{node_id}.toml"
    path.write_text(text)
    return path


@contextmanager
def standalone_drive(config: Path, interface: str, channel: str) -> Iterator[subprocess.Popen[str]]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    proc = subprocess.Popen(
        [sys.executable, "-m", "firmware_sim", str(config), "-i", interface, "-c", channel],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
