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

Both are streamed from the log group of chunks by group (:func:`export_log_frames`,
:func:`write_log_samples_csv` over :func:`dob_hil.log.stream.open_stream`), so a log of any length
is exported in bounded memory: a first pass over the frames' ids and times finds our transmitted
ids (for the echoes) and the first timestamp (for the wall clock), the second writes. Each
channel's frames are in non-decreasing time (one clock per log, log time = frame timestamp); the
two channels are merged by timestamp (classic first on a tie). A frame that goes back in time
within its channel (a foreign capture) is written where the file holds it, and counted.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from itertools import chain
from pathlib import Path
from typing import Any, Final

import can
import numpy as np
import numpy.typing as npt

from dob_hil.analysis.frames import message_of_row
from dob_hil.errors import DobHilError
from dob_hil.log.schemas import CAN_TX, TOPIC_CAN, TOPIC_CAN_FD, TOPIC_SAMPLE
from dob_hil.log.stream import open_stream
from dob_hil.log.wallclock import wall_offset_ns

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


def write_messages(messages: Iterable[can.Message], path: Path, fmt: str) -> int:
    """Write ``messages`` to ``path`` in ``fmt`` (blf, asc, csv) with python-can's writers."""
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
            for msg in messages:
                writer.on_message_received(msg)
                count += 1
    except OSError as exc:
        raise ExportError(f"{path}: cannot write: {exc}") from exc
    return count


_FRAME_FIELDS = ("timestamp_ns", "arbitration_id", "direction", "dlc", "flags", "data")


@dataclass
class FrameExport:
    """What :func:`export_log_frames` wrote and met."""

    frames: int = 0
    echoes: int = 0  # received copies of our own frames left out
    out_of_order: int = 0  # frames earlier than their channel's previous one (written in file order)
    warnings: list[str] = field(default_factory=list)  # the reader's, once each

    def warn(self, warnings: Iterable[str]) -> None:
        self.warnings.extend(w for w in warnings if w not in self.warnings)


def _survey_frames(path: Path, result: FrameExport) -> tuple[dict[str, set[int]], int | None, dict[str, Any]]:
    """Pass 1: per channel the ids we sent, the first timestamp, the log's metadata."""
    names = ("timestamp_ns", "arbitration_id", "direction")
    tx_ids: dict[str, set[int]] = {TOPIC_CAN: set(), TOPIC_CAN_FD: set()}
    first: list[int] = []
    with open_stream(path, {TOPIC_CAN: names, TOPIC_CAN_FD: names}, events=False) as stream:
        for blocks in stream.blocks():
            for topic, block in ((TOPIC_CAN, blocks.frames), (TOPIC_CAN_FD, blocks.fd_frames)):
                if len(block):
                    tx_ids[topic].update(
                        np.unique(block["arbitration_id"][block["direction"] == CAN_TX]).tolist()
                    )
                    first.append(int(block["timestamp_ns"].min()))
        result.warn(stream.warnings)
        metadata = stream.header().metadata
    return tx_ids, (min(first) if first else None), metadata


def _channel_rows(
    path: Path, topic: str, tx_ids: set[int], offset_ns: int, result: FrameExport
) -> Iterator[tuple[Any, ...]]:
    """Pass 2, one channel: its frames without our echoes, as rows with wall-clock timestamps."""
    ids = np.asarray(sorted(tx_ids), dtype=np.int64)
    last_ns: int | None = None
    with open_stream(path, {topic: None}, events=False) as stream:
        for blocks in stream.blocks():
            block = blocks.frames if topic == TOPIC_CAN else blocks.fd_frames
            echo = (block["direction"] != CAN_TX) & np.isin(block["arbitration_id"], ids)
            result.echoes += int(np.count_nonzero(echo))
            kept = block[~echo]
            if len(kept) == 0:
                continue
            t = kept["timestamp_ns"].astype(np.int64)
            start = np.asarray([last_ns if last_ns is not None else t[0]], dtype=np.int64)
            result.out_of_order += int(np.count_nonzero(np.diff(np.concatenate([start, t])) < 0))
            last_ns = max(int(t.max()), last_ns if last_ns is not None else int(t[0]))
            columns = [kept[name].tolist() for name in _FRAME_FIELDS[1:]]
            yield from zip((t + offset_ns).tolist(), *columns, strict=True)
        result.warn(stream.warnings)


def export_log_frames(path: Path, out: Path, fmt: str) -> FrameExport:
    """Stream every frame of the log at ``path`` into ``out`` (module docstring)."""
    result = FrameExport()
    tx_ids, first_ns, metadata = _survey_frames(path, result)
    offset_ns = wall_offset_ns(metadata, first_ns)
    classic = _channel_rows(path, TOPIC_CAN, tx_ids[TOPIC_CAN], offset_ns, result)
    fd = _channel_rows(path, TOPIC_CAN_FD, tx_ids[TOPIC_CAN_FD], offset_ns, result)
    rows = heapq.merge(classic, fd, key=lambda row: row[0])  # classic first on a tie
    result.frames = write_messages((message_of_row(row, None) for row in rows), out, fmt)
    return result


def write_log_samples_csv(path: Path, out: Path) -> tuple[int, list[str]]:
    """Stream the samples of the log at ``path`` into ``out`` as CSV; (rows, the reader's warnings)."""
    with open_stream(path, {TOPIC_SAMPLE: None}, events=False) as stream:
        empty = stream.header().samples  # its layout: the header of a log without samples
        n = write_samples_csv(chain([empty], (blocks.samples for blocks in stream.blocks())), out)
        return n, list(stream.warnings)


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


def write_samples_csv(samples: StructArray | Iterable[StructArray], path: Path) -> int:
    """Write the samples (one array, or blocks of them) as CSV (module docstring); returns the
    row count. Blocks are written as they come: memory is bounded by a block."""
    blocks: Iterable[StructArray] = [samples] if isinstance(samples, np.ndarray) else samples
    n = 0
    try:
        with path.open("w", encoding="utf-8", newline="") as f:
            header = False
            for block in blocks:
                columns = scalar_columns(block)
                if not header:
                    f.write(",".join(name for name, _ in columns) + "\n")
                    header = True
                for start in range(0, len(block), ROWS_PER_BLOCK):
                    stop = start + ROWS_PER_BLOCK
                    texts = [_formatted(values[start:stop]) for _, values in columns]
                    f.write("".join(",".join(row) + "\n" for row in zip(*texts, strict=True)))
                n += len(block)
    except OSError as exc:
        raise ExportError(f"{path}: cannot write: {exc}") from exc
    return n
