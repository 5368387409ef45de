"""A log rewritten in the other message layout (``dob-hil export --format mcap --log-layout``).

Blocks to samples gives Foxglove a log whose every field plots against time; samples to blocks
makes an existing log about 40 % smaller. The conversion works on the MCAP records, not on the
arrays, so every record keeps its bytes, its channel's sequence number and its log time: the
blocks are expanded into one Message record per record (sequence = the block's + its index, log
and publish time = the record's own time, its first field), and the result goes through the
writer's own :class:`~dob_hil.log.chunked_file.ChunkedFile`, which forms the blocks of a block
target as a run does. Schemas, channels, metadata (``log_format`` says the new layout) and
attachments are carried over. A damaged log converts as far as it reads; the reader's warnings
are returned.
"""

from __future__ import annotations

import mmap
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import numpy as np
import numpy.typing as npt

import dob_hil
from dob_hil.log.blocks import block_counts, first_record_offsets, gather_ints
from dob_hil.log.chunked_file import ChunkedFile
from dob_hil.log.reader import _Reader, map_log, record_fields
from dob_hil.log.schemas import (
    CDR_HEADER_U32,
    MESSAGE_LAYOUTS,
    MESSAGE_RECORD_OVERHEAD,
    OP_MESSAGE,
    body_size,
    channel_specs,
    record_length,
)
from dob_hil.log.writer import DEFAULT_BLOCK_CHUNK_SIZE_BYTES, DEFAULT_CHUNK_SIZE_BYTES, attachment_media_type

RECORDS_PER_FEED: Final = 512  # records handed to the file at once (a chunk overshoots by at most these)


@dataclass
class Converted:
    records: int = 0  # Message records read (a block counts its records)
    warnings: list[str] = field(default_factory=list)


def _expanded(buf: bytes, offset: int, count: int, stride: int, body: int) -> tuple[bytes, int]:
    """The ``count`` records of the block at ``offset`` of ``buf`` as Message records (bytes, size)."""
    at = np.asarray([offset], dtype=np.int64)
    channel = int(gather_ints(buf, "<u2", at + 9)[0])
    seq = int(gather_ints(buf, "<u4", at + 11)[0])
    size = MESSAGE_RECORD_OVERHEAD + 4 + body
    rec = np.zeros(count, dtype=np.dtype({
        "names": ["op", "length", "channel", "seq", "log_time", "publish_time", "cdr"],
        "formats": ["u1", "<u8", "<u2", "<u4", "<u8", "<u8", "<u4"],
        "offsets": [0, 1, 9, 11, 15, 23, 31], "itemsize": size,
    }))  # fmt: skip
    starts = first_record_offsets(at)[0] + np.arange(count, dtype=np.int64) * stride
    rows = np.frombuffer(buf, dtype=np.uint8)[starts[:, None] + np.arange(body)]
    rec["op"], rec["length"], rec["channel"] = OP_MESSAGE, size - 9, channel
    rec["seq"] = (seq + np.arange(count, dtype=np.int64)) & 0xFFFFFFFF
    rec["log_time"] = rec["publish_time"] = rows[:, :8].copy().view("<u8")[:, 0]  # the record's time
    rec["cdr"] = CDR_HEADER_U32
    rec.view(np.uint8).reshape(count, size)[:, MESSAGE_RECORD_OVERHEAD + 4 :] = rows
    return rec.tobytes(), size


def convert_layout(source: Path, target: Path, message_layout: str) -> Converted:
    """Write ``source``'s records to ``target`` in ``message_layout`` ("samples" or "blocks")."""
    if message_layout not in MESSAGE_LAYOUTS:
        raise ValueError(f"message layout {message_layout!r}")
    mm = map_log(source)
    try:
        return _convert(mm, source, target, message_layout)
    finally:
        mm.close()


def _convert(mm: mmap.mmap, source: Path, target: Path, message_layout: str) -> Converted:
    reader = _Reader(mm, str(source), None, True)
    reader._learn_channels()
    layout = reader._layout()
    blocks = reader.block_channels()  # source channel id -> stride
    bodies = {}
    for cid in blocks:
        channel = reader.fmap.channels[cid]
        bodies[cid] = body_size(record_fields(reader.fmap.schemas[channel.schema_id]))
    specs = channel_specs(layout, message_layout)
    by_topic = {spec.topic: spec.key for spec in specs}
    # source channel id -> the target's (dob_hil's topics only; a capture may number them otherwise)
    ids = {c.id: by_topic[c.topic] for c in reader.fmap.channels.values() if c.topic in by_topic}
    # a fixed-size channel's record length (a record of another length is damage: skipped, as read_log does)
    sizes = {spec.key: record_length(spec.fields) for spec in specs if spec.fields is not None}
    out = Converted()
    chunk_bytes = DEFAULT_BLOCK_CHUNK_SIZE_BYTES if message_layout == "blocks" else DEFAULT_CHUNK_SIZE_BYTES
    file = ChunkedFile(str(target), f"dob_hil/{dob_hil.__version__} (convert)", specs, "zstd")
    try:
        fmap = reader.fmap
        for name, blob in fmap.attachments.items():
            file.add_attachment(0, 0, name, attachment_media_type(name), blob)
        for group in reader._groups():
            table = reader._table(group)
            keep = np.isin(table.channels, list(ids))
            offsets, channels, lengths = table.offsets[keep], table.channels[keep], table.lengths[keep]
            plan = _Plan(blocks, bodies, ids, sizes)
            for piece, starts in _pieces(group.buf, offsets, channels, lengths, plan, out):
                file.add_messages(piece, 0, len(piece), starts)
                if file.chunk_bytes >= chunk_bytes:
                    file.finish_chunk()
            reader._release(group)
        for name, data in fmap.metadata.items():
            new = {**data, "message_layout": message_layout} if name == "log_format" else data
            file.add_metadata(name, new)
        file.finish()
    except BaseException:
        file.close()
        target.unlink(missing_ok=True)
        raise
    out.warnings = [*reader.warnings, *out.warnings]
    return out


@dataclass(frozen=True)
class _Plan:
    blocks: dict[int, int]  # the source's block channels: id -> record stride
    bodies: dict[int, int]  # their record body sizes
    ids: dict[int, int]  # source channel id -> target channel id
    sizes: dict[int, int]  # target channel id -> record length field (fixed-size channels)


def _pieces(
    buf: bytes,
    offsets: npt.NDArray[np.int64],
    channels: npt.NDArray[np.int64],
    lengths: npt.NDArray[np.int64],
    plan: _Plan,
    out: Converted,
) -> list[tuple[bytes, list[int]]]:
    """The group's Message records, one record per record, in runs of at most RECORDS_PER_FEED,
    with the target's channel ids."""
    blocks, bodies, ids, sizes = plan.blocks, plan.bodies, plan.ids, plan.sizes
    pieces: list[tuple[bytes, list[int]]] = []
    is_block = np.isin(channels, list(blocks))
    run: list[int] = []  # indexes of plain records, copied as they are

    def flush_run() -> None:
        for i in range(0, len(run), RECORDS_PER_FEED):
            part = run[i : i + RECORDS_PER_FEED]
            data = bytearray(b"".join(buf[int(offsets[j]) : int(offsets[j] + 9 + lengths[j])] for j in part))
            starts = np.cumsum([0] + [int(9 + lengths[j]) for j in part[:-1]]).astype(np.int64)
            _set_channels(data, starts, [ids[int(channels[j])] for j in part])
            pieces.append((bytes(data), starts.tolist()))
        out.records += len(run)
        run.clear()

    wrong = 0
    for i in range(len(offsets)):
        if not is_block[i]:
            size = sizes.get(ids[int(channels[i])])
            if size is not None and int(lengths[i]) != size:
                wrong += 1
                continue
            run.append(i)
            continue
        flush_run()
        cid = int(channels[i])
        (count,) = block_counts(buf, offsets[i : i + 1], lengths[i : i + 1], blocks[cid]).tolist()
        if count < 0:
            out.warnings.append(f"channel {cid}: a block of the wrong length or encoding skipped")
        if count <= 0:
            continue
        data, size = _expanded(buf, int(offsets[i]), count, blocks[cid], bodies[cid])
        if ids[cid] != cid:
            patched = bytearray(data)
            _set_channels(patched, np.arange(count, dtype=np.int64) * size, [ids[cid]] * count)
            data = bytes(patched)
        for j in range(0, count, RECORDS_PER_FEED):
            n = min(RECORDS_PER_FEED, count - j)
            pieces.append((data[j * size : (j + n) * size], list(range(0, n * size, size))))
        out.records += count
    flush_run()
    if wrong:
        out.warnings.append(f"{wrong} messages of the wrong length skipped")
    return pieces


def _set_channels(data: bytearray, starts: npt.NDArray[np.int64], ids: list[int]) -> None:
    """Write the channel id of each Message record starting at ``starts`` of ``data``."""
    view = np.ndarray((len(data) - 1,), "<u2", data, 0, (1,))
    view[starts + 9] = ids


__all__ = ["Converted", "convert_layout"]
