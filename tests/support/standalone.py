"""``python -m firmware_sim`` in its own process for the real-time tests, started and stopped
cleanly: the host is only started once the drive says it is listening (an enable sent before that
would be lost), and the drive's ground truth can be collected from its UDP truth port."""

from __future__ import annotations

import os
import random
import socket
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from dob_hil.scenarios import scenario_variant
from firmware_sim import process
from firmware_sim.process import StandaloneDrive
from firmware_sim.truth import GroundTruth, decode_truth

REPO_ROOT = Path(__file__).resolve().parents[2]


def paper_config_for_node(tmp_path: Path, node_id: int, *, patience_periods: int = 10_000) -> Path:
    """paper-step with its own node id and patient timeouts: widened from 10 periods (3 ms) to 3 s
    so that a stall of a loaded CI machine (2-36 ms measured on this kind of machine, far more with
    CPU hogs beside the tests) does not end a test run."""
    return scenario_variant("paper-step", tmp_path, node_id=node_id, patience_periods=patience_periods)


def node_id_for_worker(count: int = 1) -> int:
    """A random node id of this xdist worker's own range, such that the ``count`` ids from it
    (the nodes of a several-axis drive) all lie in the range (a second line of defence: the
    traffic is already private to this worker's network namespace and the test's own port,
    udp_isolation)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    index = int(worker[2:]) if worker[2:].isdigit() else 0
    low = 2 + 7 * (index % 2)  # the native protocol has nodes 0..15: ranges 2..8 and 9..15
    return random.randint(low, low + 7 - count)


class TruthReceiver:
    """Collects the drive's ground-truth datagrams (one per period) on a free local UDP port."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)  # no loss while busy
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port: int = self.sock.getsockname()[1]
        self.samples: list[GroundTruth] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="truth-rx", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            self.samples.append(decode_truth(data))

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.sock.close()


@contextmanager
def standalone_drive(
    config: Path, channel: str, *, truth_port: int | None = None, ready_timeout_s: float = 20.0
) -> Iterator[StandaloneDrive]:
    """firmware_sim.process.standalone_drive over udp_multicast, as the tests use it: no busy-wait
    (the tests share the CPUs), this checkout's firmware_sim first on the path."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    try:
        with process.standalone_drive(
            config, "udp_multicast", channel, spin_us=0, truth_port=truth_port, env=env,
            ready_timeout_s=ready_timeout_s,
        ) as drive:  # fmt: skip
            yield drive
    except RuntimeError as exc:
        pytest.fail(str(exc))
