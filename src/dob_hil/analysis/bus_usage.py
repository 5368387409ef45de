"""Bus load measured from the logged frames (classic CAN).

Each frame's length in bits: worst case with bit stuffing (:func:`dob_hil.link.busload.frame_bits`,
Davis et al. 2007 eq. 2) and nominal without stuffing (``g + 8 n + 13``). The load over a window
is the bus time of its frames divided by the window's duration. The duration is taken from the
samples' instants (``time_ns``: simulated time in lockstep, the real schedule in real time), so a
lockstep run, which runs faster than real time, reports the load its traffic would put on a real
bus at the nominal period.

Frames are selected by their timestamps (``timestamp_ns``); :func:`clock_offset_ns` finds the
samples' clock they line up with (and the offset) through the commands, one per sample. The
window of samples ``first..end`` holds the frames after the command of sample ``first - 1`` up to
the command of the last sample. Received copies of our own transmitted ids (udp_multicast
delivers a process its own frames) are not counted twice; error frames occupy no data frame
and are not counted; CAN FD frames are counted in ``fd_frames`` only (their length depends on
the data-phase bitrate, which the log does not record).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from dob_hil.link.busload import CONTROL_BITS_EXTENDED_ID, CONTROL_BITS_STANDARD_ID, frame_bits
from dob_hil.log.schemas import CAN_FLAG_ERROR, CAN_FLAG_EXTENDED, CAN_FLAG_REMOTE, CAN_TX

StructArray = npt.NDArray[np.void]
NOMINAL_TRAILER_BITS = 13
TIE_NS = 2_000  # pairings whose spreads differ less than this are equally good

# Worst-case and nominal bits by frame class ``9 * extended + data bytes`` (0..17).
_WORST = np.array([frame_bits(n, extended_id=ext) for ext in (False, True) for n in range(9)], dtype=np.int64)
_NOMINAL = np.array(
    [
        g + 8 * n + NOMINAL_TRAILER_BITS
        for g in (CONTROL_BITS_STANDARD_ID, CONTROL_BITS_EXTENDED_ID)
        for n in range(9)
    ],
    dtype=np.int64,
)


def counted_frames(frames: StructArray) -> npt.NDArray[np.bool_]:
    """Mask of the frames that occupied the bus once: no error frames, no received own echoes."""
    flags = frames["flags"]
    keep = (flags & CAN_FLAG_ERROR) == 0
    tx = frames["direction"] == CAN_TX
    if tx.any():
        tx_ids = np.unique(frames["arbitration_id"][tx])
        keep &= tx | ~np.isin(frames["arbitration_id"], tx_ids)
    return np.asarray(keep, dtype=np.bool_)


def frame_classes(frames: StructArray) -> npt.NDArray[np.intp]:
    """``9 * extended + data bytes`` of each frame (a remote frame carries no data bytes)."""
    flags = frames["flags"]
    data_bytes = np.minimum(frames["dlc"], 8)
    data_bytes[(flags & CAN_FLAG_REMOTE) != 0] = 0
    return np.asarray(9 * ((flags & CAN_FLAG_EXTENDED) != 0) + data_bytes, dtype=np.intp)


def frame_bit_counts(frames: StructArray) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(worst-case bits, nominal bits) of each frame."""
    classes = frame_classes(frames)
    return _WORST[classes], _NOMINAL[classes]


def _offset_against(clock: npt.NDArray[np.int64], tx_frames: npt.NDArray[np.int64]) -> tuple[float, int]:
    """(spread, offset) of the best in-order pairing of ``clock`` with the transmitted frames.

    A period may transmit several frames (one COMMAND per axis of a multi-axis drive, a SYNC
    beside an RPDO): the frames are paired by burst, the first frame of each, a burst being
    frames less than half a period after the previous one.
    """
    tx_frames = burst_starts(tx_frames, clock)
    head = min(len(clock), len(tx_frames), 1024)
    shifts = min(len(tx_frames) - head, 64) + 1
    windows = np.lib.stride_tricks.sliding_window_view(tx_frames[: head + shifts - 1], head)
    d = windows - clock[:head]  # (shifts, head)
    p10, p50, p90 = np.percentile(d, [10.0, 50.0, 90.0], axis=1)
    spread = p90 - p10
    # strictly periodic stamps pair equally well one period off: of the tightest pairings
    # (within TIE_NS) take the smallest offset
    tight = np.flatnonzero(spread <= spread.min() + TIE_NS)
    best = int(tight[np.argmin(np.abs(p50[tight]))])
    return float(spread[best]), int(p50[best])


def burst_starts(tx_sorted: npt.NDArray[np.int64], clock: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """The first of each burst of ``tx_sorted``: frames within half the clock's median period of
    the previous frame belong to its burst."""
    if len(clock) < 2 or len(tx_sorted) < 2:
        return tx_sorted
    half_period = int(np.median(np.diff(clock[: min(len(clock), 1024)]))) // 2
    if half_period <= 0:
        return tx_sorted
    keep = np.empty(len(tx_sorted), dtype=np.bool_)
    keep[0] = True
    keep[1:] = np.diff(tx_sorted) >= half_period
    return tx_sorted[keep]


def clock_offset_ns(samples: StructArray, frames: StructArray) -> tuple[str, int] | None:
    """(sample clock field, ``frame timestamp - that clock``), or None without commands.

    The frames are stamped on the samples' clock (lockstep: the simulated time of ``time_ns``;
    real time: the loop clock of ``tx_time_ns``) or on the bus's own clock. The first (up to)
    1024 samples of each candidate clock are paired in order with the transmitted frames, trying
    the first 64 shifts (the enable sequence sends frames before the first command); the clock
    and shift whose differences spread least win, and every sample then refines the offset by
    pairing with its nearest transmitted frame.
    """
    tx_frames = np.sort(frames["timestamp_ns"][frames["direction"] == CAN_TX].astype(np.int64))
    if len(samples) == 0 or len(tx_frames) == 0:
        return None
    best: tuple[float, str, int] | None = None
    for name in ("time_ns", "tx_time_ns"):
        clock = samples[name].astype(np.int64)
        if clock[0] <= 0 and name == "tx_time_ns":
            continue
        spread, offset = _offset_against(clock, tx_frames)
        if best is None or spread < best[0]:
            best = (spread, name, offset)
    if best is None:
        return None
    _, name, offset = best
    clock = samples[name].astype(np.int64)
    pick = clock[np.linspace(0, len(clock) - 1, min(len(clock), 4096)).astype(np.int64)] + offset
    pos = np.clip(np.searchsorted(tx_frames, pick), 1, max(len(tx_frames) - 1, 1))
    before = tx_frames[pos - 1]
    after = tx_frames[np.minimum(pos, len(tx_frames) - 1)]
    nearest = np.where(np.abs(after - pick) < np.abs(before - pick), after, before)
    return name, offset + int(np.median(nearest - pick))


def bus_load(
    samples: StructArray,
    frames: StructArray,
    fd_frames: StructArray,
    first: int,
    period_ns: int,
    bitrate_bps: int | None,
) -> dict[str, Any] | None:
    """Mean bus load over the samples ``first..end`` (module docstring); None without frames or
    bitrate. The frames of the window are those after the command of sample ``first - 1`` up to
    the command of the last sample. Keys: worst_case and nominal (fractions of the bus), frames,
    frames_per_period, bits_per_period_worst_case, bitrate_bps, fd_frames."""
    n_periods = len(samples) - first
    if n_periods <= 0 or len(frames) == 0 or not bitrate_bps:
        return None
    aligned = clock_offset_ns(samples, frames)
    if aligned is None:
        return None
    name, offset = aligned
    clock = samples[name]
    start = max(int(clock[first - 1]) + offset, 0) if first > 0 else 0
    end = max(int(clock[-1]) + offset, 0)
    ts = frames["timestamp_ns"]  # uint64; compared with the bounds without a copy
    in_window = (ts > start) if first > 0 else (ts >= 0)
    in_window &= ts <= end
    in_window &= counted_frames(frames)
    histogram = np.bincount(frame_classes(frames)[in_window], minlength=len(_WORST))
    fd_in = 0
    if len(fd_frames):
        fts = fd_frames["timestamp_ns"]
        fd_in = int(np.count_nonzero((fts >= start) & (fts <= end)))
    return load_figures(histogram, n_periods, period_ns, bitrate_bps, fd_in)


def load_figures(
    histogram: npt.NDArray[np.int64], n_periods: int, period_ns: int, bitrate_bps: int, fd_frames: int
) -> dict[str, Any]:
    """The keys of :func:`bus_load` from the counted frames of a window of ``n_periods`` periods
    (``histogram``: frames per class of :func:`frame_classes`) and the FD frames in it."""
    worst_bits = int(histogram @ _WORST)
    nominal_bits = int(histogram @ _NOMINAL)
    n_frames = int(histogram.sum())
    duration_s = n_periods * period_ns * 1e-9
    return {
        "worst_case": worst_bits / bitrate_bps / duration_s,
        "nominal": nominal_bits / bitrate_bps / duration_s,
        "frames": n_frames,
        "frames_per_period": n_frames / n_periods,
        "bits_per_period_worst_case": worst_bits / n_periods,
        "bitrate_bps": int(bitrate_bps),
        "fd_frames": fd_frames,
    }
