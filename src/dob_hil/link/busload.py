"""Worst-case classic-CAN bus load of the native protocol's cyclic traffic.

Frame length with worst-case bit stuffing, from Davis, Burns, Bril, Lukkien, "Controller Area
Network (CAN) schedulability analysis: Refuted, revisited and revised", Real-Time Systems 35
(2007), eq. 2::

    bits = g + 8 n + 13 + floor((g + 8 n - 1) / 4)

``n`` data bytes, ``g = 34`` control bits for an 11-bit id (54 for a 29-bit id) of which
``g + 8 n - 1`` are exposed to stuffing; the 13 are the CRC delimiter, ACK, end of frame and the
3-bit interframe space, which are not stuffed.

Per control period the loop puts one FEEDBACK (drive->host) and one COMMAND (host->drive) on the
bus per axis (node); each node's HEARTBEAT (``heartbeat_hz``) is amortised over the period. FAULT and CONTROL
frames are sporadic (start, stop, faults) and not counted.
"""

from __future__ import annotations

from dataclasses import dataclass

from dob_hil.config import DriveConfig
from dob_hil.errors import ConfigError, ProtocolError
from dob_hil.link.protocol import DLC, FrameKind

CONTROL_BITS_STANDARD_ID = 34  # g for 11-bit identifiers
CONTROL_BITS_EXTENDED_ID = 54  # g for 29-bit identifiers
UNSTUFFED_TRAILER_BITS = 13  # CRC delimiter, ACK slot + delimiter, EOF (7), interframe space (3)
DEFAULT_HEARTBEAT_HZ = 10.0


def frame_bits(data_bytes: int, *, extended_id: bool = False) -> int:
    """Worst-case length in bits of a classic CAN data frame with ``data_bytes`` bytes (0..8)."""
    if isinstance(data_bytes, bool) or not isinstance(data_bytes, int) or not 0 <= data_bytes <= 8:
        raise ProtocolError(f"data_bytes: a classic CAN frame carries 0..8 bytes, got {data_bytes!r}")
    g = CONTROL_BITS_EXTENDED_ID if extended_id else CONTROL_BITS_STANDARD_ID
    stuffable = g + 8 * data_bytes
    return stuffable + UNSTUFFED_TRAILER_BITS + (stuffable - 1) // 4


@dataclass(frozen=True)
class BusLoad:
    """Worst-case load of one control period on the bus."""

    bitrate_bps: int
    period_ns: int
    heartbeat_hz: float
    frame_bits: dict[str, int]  # worst-case bits of each frame kind counted
    frames_per_period: dict[str, float]  # how many of each per period (heartbeat: a fraction)
    bits_per_period: float
    time_per_period_us: float  # bus time the frames occupy per period
    fraction: float  # time_per_period / period; above 1.0 the traffic does not fit

    @property
    def percent(self) -> float:
        return 100.0 * self.fraction

    def breakdown(self) -> str:
        """A human-readable table of the computation."""
        bit_us = 1e6 / self.bitrate_bps
        lines = [
            f"worst-case bus load at {self.bitrate_bps} bit/s, period {self.period_ns / 1000:g} us "
            f"(1 bit = {bit_us:g} us, stuffing per Davis et al. 2007 eq. 2):"
        ]
        for name, bits in self.frame_bits.items():
            per = self.frames_per_period[name]
            lines.append(f"  {name:<10} {bits:4d} bit x {per:.6g} per period = {bits * per * bit_us:9.3f} us")
        lines.append(
            f"  total      {self.bits_per_period:.6g} bit = {self.time_per_period_us:.3f} us "
            f"of {self.period_ns / 1000:g} us = {self.percent:.1f}%"
        )
        return "\n".join(lines)


def cyclic_bus_load(
    bitrate_bps: int,
    period_ns: int,
    frames: dict[str, tuple[int, float]],
    *,
    heartbeat_hz: float = 0.0,
    extended_id: bool = False,
) -> BusLoad:
    """Worst-case load of a profile's cyclic traffic: ``frames`` maps a frame's name to
    (data bytes, frames per period). ``heartbeat_hz`` is only recorded (count the heartbeat in
    ``frames`` as ``heartbeat_hz * period`` per period)."""
    if isinstance(period_ns, bool) or not isinstance(period_ns, int) or period_ns <= 0:
        raise ConfigError("plant.period_us", f"the control period must be > 0 ns, got {period_ns!r}")
    if bitrate_bps <= 0:
        raise ConfigError("drive.bitrate_bps", f"must be > 0, got {bitrate_bps}")
    bits = {name: frame_bits(n_bytes, extended_id=extended_id) for name, (n_bytes, _) in frames.items()}
    per_period = {name: per for name, (_, per) in frames.items()}
    total_bits = sum(bits[name] * per_period[name] for name in bits)
    time_us = total_bits * 1e6 / bitrate_bps
    return BusLoad(
        bitrate_bps=bitrate_bps,
        period_ns=period_ns,
        heartbeat_hz=heartbeat_hz,
        frame_bits=bits,
        frames_per_period=per_period,
        bits_per_period=total_bits,
        time_per_period_us=time_us,
        fraction=time_us * 1000.0 / period_ns,
    )


def worst_case_bus_load(
    drive: DriveConfig, period_ns: int, *, heartbeat_hz: float = DEFAULT_HEARTBEAT_HZ, n_axes: int = 1
) -> BusLoad:
    """Worst-case bus load of one FEEDBACK + one COMMAND per period plus the heartbeat, per axis."""
    if isinstance(period_ns, bool) or not isinstance(period_ns, int) or period_ns <= 0:
        raise ConfigError("plant.period_us", f"the control period must be > 0 ns, got {period_ns!r}")
    if not heartbeat_hz >= 0.0:
        raise ConfigError("heartbeat_hz", f"must be >= 0, got {heartbeat_hz}")
    if n_axes < 1:
        raise ConfigError("plant.B", f"a drive has at least one axis, got {n_axes}")
    frames = {
        FrameKind.FEEDBACK.name: (DLC[FrameKind.FEEDBACK], float(n_axes)),
        FrameKind.COMMAND.name: (DLC[FrameKind.COMMAND], float(n_axes)),
        FrameKind.HEARTBEAT.name: (DLC[FrameKind.HEARTBEAT], n_axes * heartbeat_hz * period_ns * 1e-9),
    }
    return cyclic_bus_load(drive.bitrate_bps, period_ns, frames, heartbeat_hz=heartbeat_hz)


def refuse_overload(load: BusLoad, *, max_fraction: float = 1.0) -> BusLoad:
    """``load``, or a ConfigError naming the load, the bitrate and the period above ``max_fraction``."""
    if load.fraction > max_fraction:
        raise ConfigError(
            "drive.bitrate_bps",
            f"worst-case bus load {load.percent:.0f}% > {100.0 * max_fraction:.0f}% at "
            f"{load.bitrate_bps} bit/s and period {load.period_ns / 1000:g} us "
            f"({load.bits_per_period:.1f} bit = {load.time_per_period_us:.1f} us per period); "
            "raise the bitrate or the period",
        )
    return load


def check_bus_load(
    drive: DriveConfig,
    period_ns: int,
    *,
    heartbeat_hz: float = DEFAULT_HEARTBEAT_HZ,
    max_fraction: float = 1.0,
) -> BusLoad:
    """:func:`worst_case_bus_load`, refusing a load above ``max_fraction`` with a ConfigError."""
    return refuse_overload(worst_case_bus_load(drive, period_ns, heartbeat_hz=heartbeat_hz),
                           max_fraction=max_fraction)  # fmt: skip
