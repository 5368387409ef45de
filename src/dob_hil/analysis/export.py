"""Writing a log's frames (BLF, ASC, CSV through python-can's writers) and its samples (CSV).

Frames: every classic and FD frame in timestamp order (:mod:`dob_hil.analysis.frames`), written
with ``can.BLFWriter`` (Vector binary logging format: CANalyzer/CANoe, SavvyCAN), ``can.ASCWriter``
(Vector ASCII) or ``can.CSVWriter`` (python-can's CSV: timestamp, arbitration_id, extended,
remote, error, dlc, data as base64). Timestamps are put on the wall clock from the run's start
time (:mod:`dob_hil.log.wallclock`), so BLF/ASC headers show when the run happened. Rx/Tx comes
from the logged direction where the format has a place for it (BLF, ASC; python-can's CSV has
none). The received copies of our own frames (udp_multicast echoes every frame to its sender) are
dropped, as ``replay --to-bus`` drops them: each frame that was on the bus appears once. The
channel is python-can's default (1 in BLF/ASC).

Samples: one CSV row per sample, one column per scalar: array fields become ``name_0``,
``name_1``, ...; integers in decimal, floats with 17 significant digits (they read back to the
same float64).
"""

from __future__ import annotations

from pathlib import Path
from typing import Final

import can
import numpy as np
import numpy.typing as npt

from dob_hil.analysis.frames import frame_messages
from dob_hil.errors import DobHilError
from dob_hil.log.schemas import CAN_TX

StructArray = npt.NDArray[np.void]
FRAME_FORMATS: Final = ("blf", "asc", "csv")
ROWS_PER_BLOCK = 20000


class ExportError(DobHilError):
    """The export file cannot be written."""


def default_export_path(log_path: Path, fmt: str, samples: bool) -> Path:
    """``<stem>.blf``, ``<stem>.asc``, ``<stem>-frames.csv`` or ``<stem>-samples.csv`` beside the log."""
    if samples:
        return log_path.with_name(f"{log_path.stem}-samples.csv")
    if fmt == "csv":
        return log_path.with_name(f"{log_path.stem}-frames.csv")
    return log_path.with_name(f"{log_path.stem}.{fmt}")


def own_echoes(frames: StructArray) -> npt.NDArray[np.bool_]:
    """Mask of received frames whose id we transmit: the bus's copies of our own frames."""
    tx = frames["direction"] == CAN_TX
    if not tx.any():
        return np.zeros(len(frames), dtype=np.bool_)
    ids = np.unique(frames["arbitration_id"][tx])
    return np.asarray(~tx & np.isin(frames["arbitration_id"], ids), dtype=np.bool_)


def export_frames(
    frames: StructArray, fd_frames: StructArray, *, wall_offset_ns: int = 0
) -> tuple[StructArray, StructArray, int]:
    """(frames, FD frames, echoes dropped): own echoes removed, timestamps moved by ``wall_offset_ns``."""
    echoes = own_echoes(frames)
    kept = frames[~echoes].copy()
    fd_kept = fd_frames[~own_echoes(fd_frames)].copy() if len(fd_frames) else fd_frames.copy()
    for arr in (kept, fd_kept):
        arr["timestamp_ns"] = arr["timestamp_ns"].astype(np.int64) + np.int64(wall_offset_ns)
    return kept, fd_kept, int(np.count_nonzero(echoes)) + (len(fd_frames) - len(fd_kept))


def write_frames(frames: StructArray, fd_frames: StructArray, path: Path, fmt: str) -> int:
    """Write every frame to ``path`` in ``fmt`` (blf, asc, csv); returns the frame count."""
    writers: dict[str, type[can.io.generic.MessageWriter]] = {
        "blf": can.BLFWriter,
        "asc": can.ASCWriter,
        "csv": can.CSVWriter,
    }
    if fmt not in writers:
        raise ExportError(f"--format: expected one of {', '.join(FRAME_FORMATS)}, got {fmt!r}")
    count = 0
    try:
        with writers[fmt](path) as writer:
            for msg in frame_messages(frames, fd_frames):
                writer.on_message_received(msg)
                count += 1
    except OSError as exc:
        raise ExportError(f"{path}: cannot write: {exc}") from exc
    return count


def scalar_columns(samples: StructArray) -> list[tuple[str, npt.NDArray[np.generic]]]:
    """(column name, 1-D values) for every scalar of every field, in field order."""
    columns: list[tuple[str, npt.NDArray[np.generic]]] = []
    assert samples.dtype.names is not None
    for name in samples.dtype.names:
        values = samples[name]
        if values.ndim == 1:
            columns.append((name, values))
        else:
            for j in range(values.shape[1]):
                columns.append((f"{name}_{j}", values[:, j]))
    return columns


def _formatted(values: npt.NDArray[np.generic]) -> list[str]:
    if values.dtype.kind == "f":
        return [format(v, ".17g") for v in values.tolist()]
    if values.dtype.kind == "b":
        return ["1" if v else "0" for v in values.tolist()]
    return [str(v) for v in values.tolist()]


def write_samples_csv(samples: StructArray, path: Path) -> int:
    """Write the samples as CSV (module docstring); returns the row count."""
    columns = scalar_columns(samples)
    try:
        with path.open("w", encoding="utf-8", newline="") as f:
            f.write(",".join(name for name, _ in columns) + "\n")
            for start in range(0, len(samples), ROWS_PER_BLOCK):
                stop = start + ROWS_PER_BLOCK
                texts = [_formatted(values[start:stop]) for _, values in columns]
                f.write("".join(",".join(row) + "\n" for row in zip(*texts, strict=True)))
    except OSError as exc:
        raise ExportError(f"{path}: cannot write: {exc}") from exc
    return len(samples)
