"""An MCAP file written chunk by chunk from ready-made Message records, in bulk.

The control thread packs every message as a complete MCAP Message record (:mod:`dob_hil.log.pipe`),
so a chunk's uncompressed records are those bytes back to back: :meth:`ChunkedFile.add_messages`
appends a whole run of records at once, and :meth:`ChunkedFile.finish_chunk` compresses it, builds
its MessageIndex records with numpy (the per-channel ``(log_time, offset)`` pairs gathered from
the record headers in one pass) and writes the chunk and its indexes with one ``write``, so a
killed writer leaves a file readable up to its last finished chunk. Every other record (header,
schemas, channels, attachments, metadata, chunk, chunk indexes, statistics, summary offsets,
footer) is made and serialised by the ``mcap`` library's record classes; the summary section
follows ``mcap.writer.Writer.finish``. No per-message Python object is made: the ``mcap``
library's ``add_message`` costs about 5 us per message, this about 1 us per sample.
"""

from __future__ import annotations

import errno
import os
import struct
import zlib
from collections import defaultdict
from typing import Final

import numpy as np
import numpy.typing as npt
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.writer import MCAP0_MAGIC

from dob_hil.log.blocks import gather_ints, to_blocks
from dob_hil.log.schemas import ChannelSpec, block_stride, body_size

try:  # lz4 is optional
    import lz4.frame as _lz4_frame  # type: ignore[import-untyped,unused-ignore]
except ImportError:  # pragma: no cover
    _lz4_frame = None

ZSTD_LEVEL: Final = 3
_INDEX_HEAD = struct.Struct("<BQHI")  # MessageIndex: opcode, length, channel, records length


def _end(builder: RecordBuilder) -> bytes:
    """The builder's records so far (and the builder emptied)."""
    return bytes(builder.end())  # type: ignore[no-untyped-call]


def message_index_bytes(
    channel_id: int, log_times: npt.NDArray[np.uint64], offsets: npt.NDArray[np.uint64]
) -> bytes:
    """One MessageIndex record, as ``mcap.records.MessageIndex.write`` serialises it."""
    pairs = np.empty((len(offsets), 2), dtype="<u8")
    pairs[:, 0] = log_times
    pairs[:, 1] = offsets
    length = 16 * len(offsets)
    return _INDEX_HEAD.pack(Opcode.MESSAGE_INDEX, 2 + 4 + length, channel_id, length) + pairs.tobytes()


class ChunkedFile:
    """The MCAP file: open, chunks of Message records, attachments, metadata, finish."""

    def __init__(self, path: str, library: str, channels: tuple[ChannelSpec, ...], compression: str) -> None:
        if compression not in ("zstd", "lz4", "none") or (compression == "lz4" and _lz4_frame is None):
            raise ValueError(f"compression {compression!r} is not available")
        self.compression = "" if compression == "none" else compression
        self.cctx = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
        self.fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644)
        self.pos = 0
        self.schemas: list[Schema] = []
        self.channels: list[Channel] = []
        self.chunk_indexes: list[ChunkIndex] = []
        self.attachment_indexes: list[AttachmentIndex] = []
        self.metadata_indexes: list[MetadataIndex] = []
        self.message_counts: defaultdict[int, int] = defaultdict(int)  # Message records
        self.record_counts: defaultdict[int, int] = defaultdict(int)  # records (blocks hold many)
        # the block layout: (record body size, stride) of each channel written as blocks
        self.blocks = {
            spec.key: (body_size(spec.fields), block_stride(spec.fields))
            for spec in channels
            if spec.block and spec.fields is not None
        }
        self.message_start_time: int | None = None
        self.message_end_time = 0
        self.chunk = bytearray()
        self.offsets: list[int] = []  # of the Message records in the open chunk
        self.finished = False
        builder = RecordBuilder()
        Header(profile="", library=library).write(builder)
        for spec in channels:
            schema = Schema(
                id=spec.key, name=spec.schema_name, encoding=spec.schema_encoding, data=spec.schema_data()
            )
            channel = Channel(
                id=spec.key,
                topic=spec.topic,
                message_encoding=spec.message_encoding,
                schema_id=spec.key,
                metadata={},
            )
            schema.write(builder)
            channel.write(builder)
            self.schemas.append(schema)
            self.channels.append(channel)
        self._write(MCAP0_MAGIC + _end(builder))

    # ------------------------------------------------------------------ output
    def _write(self, data: bytes | bytearray | memoryview) -> None:
        view = memoryview(data)
        while view:
            written = os.write(self.fd, view)
            view = view[written:]
            self.pos += written

    @property
    def chunk_bytes(self) -> int:
        return len(self.chunk)

    # ------------------------------------------------------------------ messages
    def add_messages(
        self, buf: bytes | bytearray | memoryview, start: int, end: int, offsets: list[int]
    ) -> None:
        """Append the Message records ``buf[start:end]`` (at ``offsets`` of ``buf``) to the open chunk."""
        base = len(self.chunk) - start
        self.chunk += buf[start:end]
        self.offsets.extend([o + base for o in offsets] if base else offsets)

    def finish_chunk(self) -> int:
        """Compress and write the open chunk with its message indexes; returns its message count."""
        if not self.offsets:
            return 0
        data = bytes(self.chunk)
        offsets = np.asarray(self.offsets, dtype=np.int64)
        records = len(self.offsets)
        block_counts: dict[int, int] = {}
        if self.blocks:
            data, block_offsets, block_counts = to_blocks(data, offsets, self.blocks)
            offsets = np.asarray(block_offsets, dtype=np.int64)
        channels = gather_ints(data, "<u2", offsets + 9)
        log_times = gather_ints(data, "<u8", offsets + 15).astype(np.uint64)
        start_time, end_time = int(log_times.min()), int(log_times.max())
        if block_counts:  # a block's records reach its publish time (its last record's log time):
            # declared as the chunk's end, so that a read by time finds every record of the chunk
            end_time = max(end_time, int(gather_ints(data, "<u8", offsets + 23).max()))
        if self.compression == "zstd":
            compressed = self.cctx.compress(data)
        elif self.compression == "lz4" and _lz4_frame is not None:
            compressed = _lz4_frame.compress(data)
        else:
            compressed = data
        builder = RecordBuilder()
        Chunk(
            compression=self.compression,
            data=compressed,
            message_start_time=start_time,
            message_end_time=end_time,
            uncompressed_crc=zlib.crc32(data),
            uncompressed_size=len(data),
        ).write(builder)
        chunk_record = _end(builder)
        chunk_start = self.pos
        index_start = chunk_start + len(chunk_record)
        parts = [chunk_record]
        index_offsets: dict[int, int] = {}
        counts: dict[int, int] = {}
        index_pos = index_start
        for channel_id in np.unique(channels).tolist():
            select = channels == channel_id
            record = message_index_bytes(
                int(channel_id), log_times[select], offsets[select].astype(np.uint64)
            )
            index_offsets[int(channel_id)] = index_pos
            index_pos += len(record)
            parts.append(record)
            counts[int(channel_id)] = int(np.count_nonzero(select))
        self._write(b"".join(parts))
        for channel_id, count in counts.items():
            self.message_counts[channel_id] += count
            self.record_counts[channel_id] += block_counts.get(channel_id, count)
        self.chunk_indexes.append(
            ChunkIndex(
                message_start_time=start_time,
                message_end_time=end_time,
                chunk_start_offset=chunk_start,
                chunk_length=len(chunk_record),
                message_index_offsets=index_offsets,
                message_index_length=index_pos - index_start,
                compression=self.compression,
                compressed_size=len(compressed),
                uncompressed_size=len(data),
            )
        )
        if self.message_start_time is None or start_time < self.message_start_time:
            self.message_start_time = start_time
        self.message_end_time = max(self.message_end_time, end_time)
        self.chunk = bytearray()
        self.offsets = []
        return records

    # ------------------------------------------------------------------ other records
    def add_attachment(
        self, create_time: int, log_time: int, name: str, media_type: str, data: bytes
    ) -> None:
        self.finish_chunk()
        builder = RecordBuilder()
        Attachment(
            create_time=create_time, log_time=log_time, name=name, media_type=media_type, data=data
        ).write(builder)
        record = _end(builder)
        self.attachment_indexes.append(
            AttachmentIndex(
                offset=self.pos,
                length=len(record),
                create_time=create_time,
                log_time=log_time,
                data_size=len(data),
                name=name,
                media_type=media_type,
            )
        )
        self._write(record)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self.finish_chunk()
        builder = RecordBuilder()
        Metadata(name=name, metadata=data).write(builder)
        record = _end(builder)
        self.metadata_indexes.append(MetadataIndex(offset=self.pos, length=len(record), name=name))
        self._write(record)

    def finish(self) -> None:
        """DataEnd, the summary section (as ``mcap.writer.Writer.finish``), footer, magic; fsync."""
        self.finish_chunk()
        builder = RecordBuilder()
        DataEnd(0).write(builder)
        self._write(_end(builder))
        summary_start = self.pos
        summary = RecordBuilder()
        offsets: list[SummaryOffset] = []

        def group(opcode: int, records: list[object]) -> None:
            start = summary.count
            for record in records:
                record.write(summary)  # type: ignore[attr-defined]
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + start,
                                         group_length=summary.count - start))  # fmt: skip

        group(Opcode.SCHEMA, list(self.schemas))
        group(Opcode.CHANNEL, list(self.channels))
        statistics = Statistics(
            message_count=sum(self.message_counts.values()),
            schema_count=len(self.schemas),
            channel_count=len(self.channels),
            attachment_count=len(self.attachment_indexes),
            metadata_count=len(self.metadata_indexes),
            chunk_count=len(self.chunk_indexes),
            message_start_time=self.message_start_time or 0,
            message_end_time=self.message_end_time,
            channel_message_counts=dict(self.message_counts),
        )
        group(Opcode.STATISTICS, [statistics])
        group(Opcode.CHUNK_INDEX, list(self.chunk_indexes))
        group(Opcode.ATTACHMENT_INDEX, list(self.attachment_indexes))
        group(Opcode.METADATA_INDEX, list(self.metadata_indexes))
        summary_offset_start = summary_start + summary.count
        for offset in offsets:
            offset.write(summary)
        summary_data = _end(summary)
        crc = zlib.crc32(summary_data)
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start), crc)
        footer = RecordBuilder()
        Footer(summary_start=summary_start, summary_offset_start=summary_offset_start, summary_crc=crc).write(
            footer
        )
        self._write(summary_data + _end(footer) + MCAP0_MAGIC)
        try:
            os.fsync(self.fd)
        except OSError as exc:  # /dev/null, a pipe or a terminal cannot be synced: nothing to lose
            if exc.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EROFS):
                raise
        self.close()
        self.finished = True

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1
