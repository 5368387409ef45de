"""The log's raw CAN frames as python-can messages, in timestamp order.

The log stores each frame with its bus timestamp (integer ns), id, direction, DLC, flags
(extended, error, remote, FD) and zero-padded data; :func:`frame_messages` rebuilds the
``can.Message`` (timestamp in seconds, ``is_rx`` from the direction, data cut to the DLC, none
for remote frames) from the classic and the FD channel merged by timestamp (stable: frames with
equal timestamps keep their file order, classic before FD).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import can
import numpy as np
import numpy.typing as npt

from dob_hil.log.schemas import CAN_FLAG_ERROR, CAN_FLAG_EXTENDED, CAN_FLAG_FD, CAN_FLAG_REMOTE, CAN_RX

StructArray = npt.NDArray[np.void]
BLOCK = 65536


def merged_order(frames: StructArray, fd_frames: StructArray) -> tuple[npt.NDArray[np.int64], int]:
    """Order of the concatenation [frames, fd_frames] by timestamp, and len(frames)."""
    ts = np.concatenate([frames["timestamp_ns"], fd_frames["timestamp_ns"]])
    return np.argsort(ts, kind="stable").astype(np.int64), len(frames)


def message_of_row(row: Any, channel: int | str | None) -> can.Message:
    """A ``can.Message`` of one frame row (timestamp_ns, id, direction, dlc, flags, data)."""
    ts_ns, arbitration_id, direction, dlc, flags, data = row
    remote = bool(flags & CAN_FLAG_REMOTE)
    fd = bool(flags & CAN_FLAG_FD)
    length = 0 if remote else min(int(dlc), len(data))
    return can.Message(
        timestamp=ts_ns * 1e-9,
        arbitration_id=int(arbitration_id),
        is_extended_id=bool(flags & CAN_FLAG_EXTENDED),
        is_remote_frame=remote,
        is_error_frame=bool(flags & CAN_FLAG_ERROR),
        channel=channel,
        dlc=int(dlc),
        data=bytes(data[:length]),
        is_fd=fd,
        is_rx=int(direction) == CAN_RX,
    )


def frame_messages(
    frames: StructArray, fd_frames: StructArray | None = None, *, channel: int | str | None = None
) -> Iterator[can.Message]:
    """Every frame of the log as a ``can.Message``, in timestamp order (module docstring).
    Built block by block, so a long log is never held as Python objects all at once."""
    fd = fd_frames if fd_frames is not None else frames[:0]
    order, n_classic = merged_order(frames, fd)
    for start in range(0, len(order), BLOCK):
        block = order[start : start + BLOCK]
        is_fd = block >= n_classic
        classic = iter(_rows(frames, block[~is_fd]))
        extra = iter(_rows(fd, block[is_fd] - n_classic))
        for from_fd in is_fd.tolist():
            yield message_of_row(next(extra) if from_fd else next(classic), channel)


def _rows(source: StructArray, rows: npt.NDArray[np.int64]) -> list[tuple[Any, ...]]:
    fields = ("timestamp_ns", "arbitration_id", "direction", "dlc", "flags", "data")
    return list(zip(*(source[f][rows].tolist() for f in fields), strict=True))
