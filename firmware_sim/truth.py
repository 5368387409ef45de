"""Ground truth for the log: the true plant state at every feedback instant. Never on the bus.

In-process it is handed to a ``truth_sink`` callable. A standalone drive
(``python -m firmware_sim ... --truth-port PORT``) sends one UDP datagram per feedback instant to
``127.0.0.1:PORT``, laid out as follows (little endian, ``40 + 8 n`` bytes)::

    offset size type     field
    0      4    bytes    magic b"FSGT"
    4      1    uint8    version (1)
    5      1    uint8    drive_state (protocol.DriveState: 0 disabled, 1 enabled, 2 fault)
    6      2    uint16   n, the number of plant states
    8      8    uint64   period_index (sample instant index; time_ns = period_index * Ts)
    16     8    int64    time_ns (simulated time of the sample instant)
    24     8    float64  disturbance_A (at the sample instant)
    32     8    float64  applied_current_A (acting just before the sample instant)
    40     8 n  float64  state[0..n-1] (true plant state at the sample instant)

:func:`decode_truth` reads it back and raises :class:`~dob_hil.errors.ProtocolError` for a
datagram that is not of this layout.

A drive of several axes (:mod:`firmware_sim.axes`, one current per plant input) sends version 2
(:class:`AxesTruth`, ``32 + 8 (2 m + n)`` bytes, read back by :func:`decode_axes_truth`)::

    offset size type     field
    0      4    bytes    magic b"FSGT"
    4      1    uint8    version (2)
    5      1    uint8    drive_state (FAULT if any axis is, ENABLED if all are, else DISABLED)
    6      2    uint16   n, the number of plant states
    8      8    uint64   period_index
    16     8    int64    time_ns
    24     2    uint16   m, the number of inputs (axes)
    26     6             zero
    32     8 m  float64  disturbance_A[0..m-1]
    ..     8 m  float64  applied_current_A[0..m-1]
    ..     8 n  float64  state[0..n-1]
"""

from __future__ import annotations

import socket
import struct
from typing import Final, NamedTuple

from dob_hil.errors import ProtocolError
from dob_hil.link.protocol import DriveState

TRUTH_MAGIC: Final = b"FSGT"
TRUTH_VERSION: Final = 1
AXES_TRUTH_VERSION: Final = 2
_HEADER: Final = struct.Struct("<4sBBHQqdd")
_AXES_HEADER: Final = struct.Struct("<4sBBHQqH6x")
TRUTH_HEADER_SIZE: Final = _HEADER.size


class GroundTruth(NamedTuple):  # built every period: a tuple is cheaper than a frozen dataclass
    period_index: int  # sample instant index
    time_ns: int  # simulated time of the sample instant
    state: tuple[float, ...]  # true plant state at the sample instant
    disturbance_A: float  # disturbance at the plant input at the sample instant
    applied_current_A: float  # drive current acting just before the sample instant (left limit)
    drive_state: DriveState


class AxesTruth(NamedTuple):
    """Ground truth of one sample instant of a drive of several axes (per input)."""

    period_index: int
    time_ns: int
    state: tuple[float, ...]  # the coupled plant's true state
    disturbance_A: tuple[float, ...]  # per input
    applied_current_A: tuple[float, ...]  # per input, acting just before the instant
    drive_state: DriveState  # FAULT if any axis is, ENABLED if all are, else DISABLED


def encode_axes_truth(truth: AxesTruth) -> bytes:
    n, m = len(truth.state), len(truth.disturbance_A)
    head = _AXES_HEADER.pack(
        TRUTH_MAGIC, AXES_TRUTH_VERSION, int(truth.drive_state), n, truth.period_index, truth.time_ns, m
    )
    return head + struct.pack(f"<{2 * m + n}d", *truth.disturbance_A, *truth.applied_current_A, *truth.state)


def decode_axes_truth(data: bytes | bytearray | memoryview) -> AxesTruth:
    """A version-2 datagram; :class:`ProtocolError` naming what is wrong otherwise."""
    raw = bytes(data)
    if len(raw) < _AXES_HEADER.size:
        raise ProtocolError(f"ground truth datagram: expected >= {_AXES_HEADER.size} bytes, got {len(raw)}")
    magic, version, drive_state, n, period_index, time_ns, m = _AXES_HEADER.unpack_from(raw)
    if magic != TRUTH_MAGIC:
        raise ProtocolError(f"ground truth datagram: bad magic {magic!r}, expected {TRUTH_MAGIC!r}")
    if version != AXES_TRUTH_VERSION:
        raise ProtocolError(f"ground truth datagram: version {version}, expected {AXES_TRUTH_VERSION}")
    size = _AXES_HEADER.size + 8 * (2 * m + n)
    if len(raw) != size:
        raise ProtocolError(
            f"ground truth datagram: {n} states and {m} inputs need {size} bytes, got {len(raw)}"
        )
    try:
        state = DriveState(drive_state)
    except ValueError:
        raise ProtocolError(f"ground truth datagram: unknown drive state {drive_state}") from None
    v = struct.unpack_from(f"<{2 * m + n}d", raw, _AXES_HEADER.size)
    return AxesTruth(period_index, time_ns, tuple(v[2 * m :]), tuple(v[:m]), tuple(v[m : 2 * m]), state)


def encode_truth(truth: GroundTruth) -> bytes:
    n = len(truth.state)
    head = _HEADER.pack(
        TRUTH_MAGIC,
        TRUTH_VERSION,
        int(truth.drive_state),
        n,
        truth.period_index,
        truth.time_ns,
        truth.disturbance_A,
        truth.applied_current_A,
    )
    return head + struct.pack(f"<{n}d", *truth.state)


def decode_truth(data: bytes | bytearray | memoryview) -> GroundTruth:
    raw = bytes(data)
    if len(raw) < _HEADER.size:
        raise ProtocolError(f"ground truth datagram: expected >= {_HEADER.size} bytes, got {len(raw)}")
    magic, version, drive_state, n, period_index, time_ns, dist, applied = _HEADER.unpack_from(raw)
    if magic != TRUTH_MAGIC:
        raise ProtocolError(f"ground truth datagram: bad magic {magic!r}, expected {TRUTH_MAGIC!r}")
    if version != TRUTH_VERSION:
        raise ProtocolError(f"ground truth datagram: version {version}, expected {TRUTH_VERSION}")
    if len(raw) != _HEADER.size + 8 * n:
        raise ProtocolError(
            f"ground truth datagram: {n} states need {_HEADER.size + 8 * n} bytes, got {len(raw)}"
        )
    try:
        state = DriveState(drive_state)
    except ValueError:
        raise ProtocolError(f"ground truth datagram: unknown drive state {drive_state}") from None
    x = struct.unpack_from(f"<{n}d", raw, _HEADER.size)
    return GroundTruth(period_index, time_ns, tuple(x), dist, applied, state)


class UdpTruthSender:
    """A ``truth_sink`` sending each :class:`GroundTruth` (or :class:`AxesTruth`) as one datagram
    to ``host:port``.

    Sending never blocks and never raises (nobody listening is fine); failures are counted.
    """

    def __init__(self, port: int, host: str = "127.0.0.1") -> None:
        if not 1 <= port <= 65535:
            raise ValueError(f"truth port must be 1..65535, got {port}")
        self.address = (host, port)
        self.send_failures = 0
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.setblocking(False)

    def __call__(self, truth: GroundTruth | AxesTruth) -> None:
        try:
            if isinstance(truth, AxesTruth):
                self._sock.sendto(encode_axes_truth(truth), self.address)
            else:
                self._sock.sendto(encode_truth(truth), self.address)
        except OSError:
            self.send_failures += 1

    def close(self) -> None:
        self._sock.close()
