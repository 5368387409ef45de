"""A tolerant map of an MCAP file: where its chunks and their message indexes are.

:func:`scan` walks the data section record by record (chunks are large, so this is a short
loop), and never raises for damage after the header: it returns what it could map and a
warning for everything it could not (truncation, records that do not parse, a summary whose
CRC fails). When the file is complete and its summary checks, a record that does not parse is
skipped by resuming at the next chunk the summary's chunk index lists.

Records follow the MCAP specification (https://mcap.dev/spec): ``opcode u8, length u64, body``.
"""

from __future__ import annotations

import bisect
import contextlib
import mmap
import struct
import zlib
from dataclasses import dataclass, field
from typing import Final

from dob_hil.errors import LogReadError

MAGIC: Final = b"\x89MCAP0\r\n"
OP_HEADER: Final = 0x01
OP_FOOTER: Final = 0x02
OP_SCHEMA: Final = 0x03
OP_CHANNEL: Final = 0x04
OP_MESSAGE: Final = 0x05
OP_CHUNK: Final = 0x06
OP_MESSAGE_INDEX: Final = 0x07
OP_CHUNK_INDEX: Final = 0x08
OP_ATTACHMENT: Final = 0x09
OP_METADATA: Final = 0x0C
OP_DATA_END: Final = 0x0F
OP_NAMES: Final = {
    0x01: "Header",
    0x02: "Footer",
    0x03: "Schema",
    0x04: "Channel",
    0x05: "Message",
    0x06: "Chunk",
    0x07: "MessageIndex",
    0x08: "ChunkIndex",
    0x09: "Attachment",
    0x0A: "AttachmentIndex",
    0x0B: "Statistics",
    0x0C: "Metadata",
    0x0D: "MetadataIndex",
    0x0E: "SummaryOffset",
    0x0F: "DataEnd",
}
FOOTER_SIZE: Final = 1 + 8 + 20
MAX_ATTACHMENT_BYTES: Final = 16 << 20  # design.json and config.toml are a few KB
# Records a data section may hold (our writer writes no Message outside a chunk; one is reported).
_DATA_SECTION_OPS: Final = frozenset({0x03, 0x04, 0x06, 0x07, 0x09, 0x0C, 0x0F})
_OP_LEN = struct.Struct("<BQ")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_CHUNK_HEAD = struct.Struct("<QQQI")  # start time, end time, uncompressed size, uncompressed crc
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # opcode, length, channel, sequence, log time, publish time


Buffer = bytes | bytearray | memoryview | mmap.mmap


class RecordError(ValueError):
    """A record whose fields do not fit its length (corrupted)."""


@dataclass(frozen=True, slots=True)
class SchemaRecord:
    id: int
    name: str
    encoding: str
    data: bytes


@dataclass(frozen=True, slots=True)
class ChannelRecord:
    id: int
    schema_id: int
    topic: str
    message_encoding: str


@dataclass(slots=True)
class ChunkRef:
    """One chunk record: where its compressed records are, and its message indexes by channel."""

    offset: int  # file offset of the chunk record (its opcode byte)
    end: int  # file offset just past the chunk record
    uncompressed_size: int
    uncompressed_crc: int
    compression: str
    data_offset: int
    data_length: int
    indexes: dict[int, tuple[int, int]] = field(default_factory=dict)  # channel -> (pairs offset, count)
    index_end: int = 0  # file offset just past its last message index record
    start_time_ns: int = 0  # log time of its first message, as the chunk record declares it
    end_time_ns: int = 0  # log time of its last message


@dataclass(slots=True)
class FileMap:
    size: int
    chunks: list[ChunkRef]
    schemas: dict[int, SchemaRecord]
    channels: dict[int, ChannelRecord]
    metadata: dict[str, dict[str, str]]
    attachments: dict[str, bytes]
    warnings: list[str]
    complete: bool  # DataEnd reached and the footer and summary check


class _Cursor:
    """Reads the fields of one record body, raising RecordError past its end."""

    def __init__(self, buf: Buffer, start: int, end: int) -> None:
        self.buf = buf
        self.pos = start
        self.end = end

    def take(self, n: int) -> int:
        pos = self.pos
        if n < 0 or pos + n > self.end:
            raise RecordError(f"field of {n} bytes runs past the record end")
        self.pos = pos + n
        return pos

    def u16(self) -> int:
        return int(_U16.unpack_from(self.buf, self.take(2))[0])

    def u32(self) -> int:
        return int(_U32.unpack_from(self.buf, self.take(4))[0])

    def u64(self) -> int:
        return int(_U64.unpack_from(self.buf, self.take(8))[0])

    def raw(self, n: int) -> bytes:
        pos = self.take(n)
        return bytes(self.buf[pos : pos + n])

    def string(self) -> str:
        try:
            return self.raw(self.u32()).decode()
        except UnicodeDecodeError as exc:
            raise RecordError(f"string is not UTF-8: {exc}") from exc

    def string_map(self) -> dict[str, str]:
        length = self.u32()
        stop = self.pos + length
        if stop > self.end:
            raise RecordError("map runs past the record end")
        out: dict[str, str] = {}
        while self.pos < stop:
            key = self.string()
            out[key] = self.string()
        if self.pos != stop:
            raise RecordError("map length disagrees with its entries")
        return out


def parse_schema(buf: Buffer, start: int, end: int) -> SchemaRecord:
    c = _Cursor(buf, start, end)
    return SchemaRecord(c.u16(), c.string(), c.string(), c.raw(c.u32()))


def parse_channel(buf: Buffer, start: int, end: int) -> ChannelRecord:
    c = _Cursor(buf, start, end)
    record = ChannelRecord(c.u16(), c.u16(), c.string(), c.string())
    c.string_map()
    return record


def _parse_chunk(buf: Buffer, offset: int, start: int, end: int) -> ChunkRef:
    c = _Cursor(buf, start, end)
    start_ns, end_ns, usize, crc = _CHUNK_HEAD.unpack_from(buf, c.take(_CHUNK_HEAD.size))
    compression = c.string()
    length = c.u64()
    data_offset = c.take(length)
    if c.pos != end:
        raise RecordError(f"records length {length} disagrees with the record length")
    return ChunkRef(
        offset, end, usize, crc, compression, data_offset, length,
        index_end=end, start_time_ns=start_ns, end_time_ns=end_ns,
    )  # fmt: skip


def _parse_message_index(buf: Buffer, start: int, end: int) -> tuple[int, int, int]:
    c = _Cursor(buf, start, end)
    channel = c.u16()
    length = c.u32()
    pairs = c.take(length)
    if c.pos != end or length % 16:
        raise RecordError(f"index length {length} is not a whole number of entries filling the record")
    return channel, pairs, length // 16


def _parse_attachment(buf: Buffer, start: int, end: int) -> tuple[str, bytes]:
    c = _Cursor(buf, start, end)
    c.u64()
    c.u64()
    name = c.string()
    c.string()
    data = c.raw(c.u64())
    crc_pos = c.pos
    crc = c.u32()
    if c.pos != end:
        raise RecordError("fields do not fill the record")
    if crc and zlib.crc32(buf[start:crc_pos]) != crc:
        raise RecordError(f"attachment {name!r} fails its CRC")
    return name, data


def _parse_metadata(buf: Buffer, start: int, end: int) -> tuple[str, dict[str, str]]:
    c = _Cursor(buf, start, end)
    name = c.string()
    data = c.string_map()
    if c.pos != end:
        raise RecordError("fields do not fill the record")
    return name, data


@dataclass(slots=True)
class _Summary:
    data_end: int  # the summary section starts here (or the footer, if no summary)
    chunk_offsets: list[int]
    schemas: dict[int, SchemaRecord]
    channels: dict[int, ChannelRecord]


def _read_summary(buf: Buffer, size: int, warnings: list[str]) -> _Summary | None:
    """The summary section if the file ends with a footer whose CRC checks, else None."""
    footer = size - len(MAGIC) - FOOTER_SIZE
    if footer < len(MAGIC) or bytes(buf[size - len(MAGIC) : size]) != MAGIC:
        return None
    op, length = _OP_LEN.unpack_from(buf, footer)
    if op != OP_FOOTER or length != 20:
        warnings.append(f"the footer at byte {footer} is corrupted (opcode {op}, length {length})")
        return None
    summary_start, summary_offset_start, crc = struct.unpack_from("<QQI", buf, footer + 9)
    if summary_start == 0:
        return _Summary(footer, [], {}, {})
    if not len(MAGIC) <= summary_start <= footer or (summary_offset_start and summary_offset_start > footer):
        warnings.append(f"the footer at byte {footer} points outside the file (summary at {summary_start})")
        return None
    if crc and zlib.crc32(buf[summary_start : footer + 25]) != crc:
        warnings.append(f"the summary section (bytes {summary_start}..{footer}) fails its CRC; not used")
        return None
    summary = _Summary(summary_start, [], {}, {})
    pos = summary_start
    stop = summary_offset_start or footer
    try:
        while pos < stop:
            op, length = _OP_LEN.unpack_from(buf, pos)
            start, end = pos + 9, pos + 9 + length
            if end > stop:
                raise RecordError("record runs past the summary section")
            if op == OP_SCHEMA:
                schema = parse_schema(buf, start, end)
                summary.schemas[schema.id] = schema
            elif op == OP_CHANNEL:
                channel = parse_channel(buf, start, end)
                summary.channels[channel.id] = channel
            elif op == OP_CHUNK_INDEX:
                summary.chunk_offsets.append(int(_U64.unpack_from(buf, start + 16)[0]))
            pos = end
    except (RecordError, struct.error) as exc:
        warnings.append(f"the summary section has a bad record at byte {pos} ({exc}); not used")
        return None
    summary.chunk_offsets.sort()
    return summary


def scan(buf: Buffer, path: str = "log") -> FileMap:
    """Map the records of an MCAP file held in ``buf`` (bytes or an mmap)."""
    size = len(buf)
    if size == 0:
        raise LogReadError(f"{path}: empty file, not an MCAP log")
    if size < len(MAGIC) or bytes(buf[: len(MAGIC)]) != MAGIC:
        raise LogReadError(f"{path}: not an MCAP file (it does not start with the MCAP magic bytes)")
    if size < len(MAGIC) + 9:
        raise LogReadError(f"{path}: MCAP file of {size} bytes ends inside its header record")
    op, length = _OP_LEN.unpack_from(buf, len(MAGIC))
    if op != OP_HEADER:
        raise LogReadError(f"{path}: unreadable MCAP header (first record has opcode {op}, expected 1)")
    if len(MAGIC) + 9 + length > size:
        raise LogReadError(f"{path}: MCAP file of {size} bytes ends inside its header record")

    warnings: list[str] = []
    summary = _read_summary(buf, size, warnings)
    fmap = FileMap(size, [], {}, {}, {}, {}, warnings, complete=False)
    data_limit = summary.data_end if summary is not None else size
    pos = len(MAGIC)
    last_chunk: ChunkRef | None = None
    data_end_found = False
    released = 0  # file pages the walk touched are dropped from this process every 64 MiB
    while True:
        if pos - released >= _RELEASE_BYTES:
            released = _release(buf, released, pos)
        if pos >= data_limit:
            if summary is None:
                _warn_truncated(fmap, pos, None)
            break
        if data_limit - pos < 9:
            _warn_truncated(fmap, pos, None)
            break
        op, length = _OP_LEN.unpack_from(buf, pos)
        start, end = pos + 9, pos + 9 + length
        problem = ""
        if op == 0 or 0x10 <= op < 0x80:
            problem = f"unknown opcode 0x{op:02x}"
        elif op not in _DATA_SECTION_OPS and op < 0x80 and pos > len(MAGIC):
            problem = f"unexpected {OP_NAMES[op]} record in the data section"
        elif end > data_limit:
            if summary is None:
                _warn_truncated(fmap, pos, op)
                break
            problem = f"length {length} runs past the data section"
        if not problem:
            try:
                if op == OP_CHUNK:
                    last_chunk = _parse_chunk(buf, pos, start, end)
                    fmap.chunks.append(last_chunk)
                elif op == OP_MESSAGE_INDEX:
                    channel, pairs, count = _parse_message_index(buf, start, end)
                    if last_chunk is not None and last_chunk.index_end == pos:
                        last_chunk.indexes[channel] = (pairs, count)
                        last_chunk.index_end = end
                elif op == OP_SCHEMA:
                    schema = parse_schema(buf, start, end)
                    fmap.schemas[schema.id] = schema
                elif op == OP_CHANNEL:
                    channel_record = parse_channel(buf, start, end)
                    fmap.channels[channel_record.id] = channel_record
                elif op == OP_METADATA:
                    name, data = _parse_metadata(buf, start, end)
                    fmap.metadata[name] = data
                elif op == OP_ATTACHMENT:
                    if length > MAX_ATTACHMENT_BYTES:
                        fmap.warnings.append(
                            f"record at byte {pos}: attachment of {length} bytes (more than "
                            f"{MAX_ATTACHMENT_BYTES}); skipped"
                        )
                    else:
                        name, blob = _parse_attachment(buf, start, end)
                        fmap.attachments[name] = blob
                elif op == OP_DATA_END:
                    if summary is not None and end != summary.data_end:
                        raise RecordError(f"it ends at byte {end}, the summary starts at {summary.data_end}")
                    data_end_found = True
                    crc = int(_U32.unpack_from(buf, start)[0]) if length >= 4 else 0
                    if crc and zlib.crc32(buf[:pos]) != crc:
                        fmap.warnings.append(f"the data section fails its CRC (DataEnd at byte {pos})")
                    break
            except (RecordError, struct.error) as exc:
                problem = f"malformed {OP_NAMES.get(op, hex(op))} record ({exc})"
        if problem and end <= data_limit and _plausible(buf, end, data_limit, summary is None):
            fmap.warnings.append(f"record at byte {pos}: {problem}; skipped")
            pos = end
            continue
        if problem:
            resume = _resume_point(summary, pos)
            if resume is None:
                lost = "the rest of the file" if summary is None else "the rest of the data section"
                fmap.warnings.append(f"record at byte {pos}: {problem}; {lost} (bytes {pos}..{size}) skipped")
                break
            fmap.warnings.append(f"record at byte {pos}: {problem}; bytes {pos}..{resume} skipped")
            pos = resume
            continue
        pos = end
    _release(buf, released, pos)
    if summary is not None:
        for record in summary.schemas.values():
            fmap.schemas.setdefault(record.id, record)
        for channel_record in summary.channels.values():
            fmap.channels.setdefault(channel_record.id, channel_record)
    if summary is None and data_end_found:
        fmap.warnings.append("the file has no valid footer: it was not closed cleanly")
    fmap.complete = summary is not None and data_end_found and not fmap.warnings
    return fmap


_RELEASE_BYTES: Final = 64 << 20


def _release(buf: Buffer, start: int, end: int) -> int:
    """Drop the mapped file pages of ``buf[start:end]`` from this process (page cache keeps them),
    so mapping a long log does not grow the resident size; returns the new release mark."""
    if isinstance(buf, mmap.mmap) and hasattr(buf, "madvise"):
        first = start // mmap.PAGESIZE * mmap.PAGESIZE
        last = end // mmap.PAGESIZE * mmap.PAGESIZE
        if last > first:
            with contextlib.suppress(OSError, ValueError):
                buf.madvise(mmap.MADV_DONTNEED, first, last - first)
    return end


def _plausible(buf: Buffer, pos: int, limit: int, truncation_possible: bool) -> bool:
    """Whether a record header at ``pos`` looks sound (used to skip one damaged record)."""
    if pos == limit:
        return True
    if limit - pos < 9:
        return truncation_possible
    op, length = _OP_LEN.unpack_from(buf, pos)
    if op == 0 or 0x10 <= op < 0x80:
        return False
    return truncation_possible or pos + 9 + length <= limit


def _resume_point(summary: _Summary | None, pos: int) -> int | None:
    if summary is None:
        return None
    i = bisect.bisect_right(summary.chunk_offsets, pos)
    return summary.chunk_offsets[i] if i < len(summary.chunk_offsets) else None


def _warn_truncated(fmap: FileMap, pos: int, op: int | None) -> None:
    size = fmap.size
    if op == OP_CHUNK:
        fmap.warnings.append(
            f"log truncated at byte {size}: the last chunk (starting at byte {pos}) is incomplete; "
            "1 chunk lost"
        )
    elif op is not None:
        fmap.warnings.append(
            f"log truncated at byte {size}: the last {OP_NAMES.get(op, hex(op))} record "
            f"(starting at byte {pos}) is incomplete"
        )
    else:
        fmap.warnings.append(f"log truncated at byte {size}: no DataEnd record, summary or footer")


@dataclass(slots=True)
class Walk:
    """The records of (part of) a decompressed chunk, read one by one."""

    offsets: list[int] = field(default_factory=list)  # Message records: offset in the chunk
    channels: list[int] = field(default_factory=list)
    lengths: list[int] = field(default_factory=list)  # record length (after opcode and length)
    log_times: list[int] = field(default_factory=list)
    schemas: list[SchemaRecord] = field(default_factory=list)
    channel_records: list[ChannelRecord] = field(default_factory=list)
    end: int = 0  # where the walk stopped
    problem: str = ""  # why it stopped early, empty if it reached ``stop``


def walk_chunk(data: bytes, start: int = 0, stop: int | None = None) -> Walk:
    """Walk the records of a decompressed chunk from ``start`` to ``stop`` (default: its end).

    The slow path, for chunks without (or with damaged) message indexes, and to check the few
    records before a chunk's first indexed message.
    """
    walk = Walk()
    pos, size = start, len(data) if stop is None else stop
    try:
        while pos < size:
            if size - pos < 9:
                raise RecordError(f"record header at chunk offset {pos} runs past the end")
            op, length = _OP_LEN.unpack_from(data, pos)
            end = pos + 9 + length
            if end > size:
                raise RecordError(f"record at chunk offset {pos} runs past the end")
            if op == OP_MESSAGE:
                if length < 22:
                    raise RecordError(f"message record at chunk offset {pos} is too short")
                _, _, channel, _, log_time, _ = _MESSAGE_HEAD.unpack_from(data, pos)
                walk.offsets.append(pos)
                walk.channels.append(channel)
                walk.lengths.append(length)
                walk.log_times.append(log_time)
            elif op == OP_SCHEMA:
                walk.schemas.append(parse_schema(data, pos + 9, end))
            elif op == OP_CHANNEL:
                walk.channel_records.append(parse_channel(data, pos + 9, end))
            pos = end
    except (RecordError, struct.error) as exc:
        walk.problem = str(exc)
    walk.end = pos
    return walk


def message_header(data: bytes, offset: int) -> tuple[int, int, int, int]:
    """(opcode, record length, channel, log time) of the Message record at ``offset``."""
    op, length, channel, _, log_time, _ = _MESSAGE_HEAD.unpack_from(data, offset)
    return int(op), int(length), int(channel), int(log_time)
