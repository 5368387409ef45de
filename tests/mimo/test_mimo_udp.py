"""The 2x2 scenario in real time across two processes: ``python -m firmware_sim`` serving both nodes
on a private udp_multicast group, ``run_session`` on the other end (behaviour only, no timing)."""

from __future__ import annotations

import socket
import threading
from pathlib import Path

import numpy as np
import pytest
from mimo_support import mimo_text
from standalone import node_id_for_worker, standalone_drive
from udp_isolation import UdpChannel

from dob_hil.config import load_config
from dob_hil.link.protocol import DriveState, FrameKind
from dob_hil.log import read_log
from dob_hil.loop.session import RunOptions, run_session
from firmware_sim.truth import AxesTruth, decode_axes_truth

pytestmark = pytest.mark.realtime


class AxesTruthReceiver:
    """The standalone multi-axis drive's ground truth (version-2 datagrams) on a local UDP port."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port: int = self.sock.getsockname()[1]
        self.samples: list[AxesTruth] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.samples.append(decode_axes_truth(self.sock.recv(4096)))
            except TimeoutError:
                continue
            except OSError:
                return

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.sock.close()


def test_two_nodes_of_a_standalone_drive_over_udp_multicast(tmp_path: Path, udp_channel: UdpChannel) -> None:
    node = node_id_for_worker(count=2)  # nodes node and node + 1
    patience = "watchdog_periods = 1000\nfeedback_timeout_periods = 1000\n"
    text = mimo_text(
        {
            "node_ids = [1, 2]": f"node_ids = [{node}, {node + 1}]",
            "watchdog_periods = 10\nfeedback_timeout_periods = 10\n": patience,
        }
    )
    cfg_path = tmp_path / "mimo.toml"
    cfg_path.write_text(text)
    config = load_config(cfg_path)
    log_path = tmp_path / "udp.mcap"
    truth = AxesTruthReceiver()
    try:
        with standalone_drive(cfg_path, udp_channel.channel, truth_port=truth.port) as proc:
            summary = run_session(
                config,
                RunOptions(interface="udp_multicast", channel=udp_channel.channel, duration_s=1.0,
                           log_path=log_path, enable_timeout_s=15.0),
            )  # fmt: skip
            assert proc.alive(), proc.last_line()
    finally:
        truth.close()
    assert summary.mode == "realtime" and summary.exit_reason == "completed"
    data = read_log(log_path)
    s, f = data.samples, data.frames
    assert len(s) == summary.planned_samples == 1000
    assert np.abs(s["dac_counts"]).max() <= 1433 and s["dac_counts"].shape[1] == 2
    for n in (node, node + 1):
        tx_cmd = f[(f["direction"] == 1) & (f["arbitration_id"] == FrameKind.COMMAND + n)]
        rx_fb = f[(f["direction"] == 0) & (f["arbitration_id"] == FrameKind.FEEDBACK + n)]
        assert len(rx_fb) >= len(s) - summary.missing_samples
        # the stop: zero current with the enable bit clear, to each node
        assert bytes(tx_cmd[-1]["data"][:2]) == b"\x00\x00" and tx_cmd[-1]["data"][2] & 0x80 == 0
    # the drive's own record: both axes enabled during the run, the coupled plant moved, and the
    # currents it applied never beyond the limit
    enabled = [t for t in truth.samples if t.drive_state is DriveState.ENABLED]
    assert enabled and all(len(t.applied_current_A) == 2 and len(t.state) == 4 for t in enabled)
    assert max(abs(a) for t in truth.samples for a in t.applied_current_A) <= 1433 / 2048
    assert max(t.state[0] for t in enabled) > 0.1
