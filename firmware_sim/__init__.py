"""firmware_sim: a simulated servo drive speaking the native CAN protocol of dob_hil.

State machine, command watchdog, DAC, encoder, plant physics and disturbance injection, on a
lockstep clock (deterministic, driven by the host's commands) or a real-time clock (its own
threads). Runs in-process on any python-can bus (``virtual`` in tests) or standalone::

    python -m firmware_sim CONFIG.toml -i udp_multicast -c 239.74.163.2 [--truth-port PORT]
"""

from __future__ import annotations

from firmware_sim.clocked import ClockKind
from firmware_sim.core import DriveStats, FrameResult
from firmware_sim.disturbance import Disturbance
from firmware_sim.drive import SimulatedDrive
from firmware_sim.truth import GroundTruth, UdpTruthSender, decode_truth, encode_truth

__all__ = [
    "ClockKind",
    "Disturbance",
    "DriveStats",
    "FrameResult",
    "GroundTruth",
    "SimulatedDrive",
    "UdpTruthSender",
    "decode_truth",
    "encode_truth",
]
