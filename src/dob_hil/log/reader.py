"""read_log: the whole log as numpy structured arrays, vectorised, tolerant of damage.

For each group of chunks (~8 MiB decompressed) the reader decompresses every chunk once, checks
its CRC, takes the chunk's MessageIndex records for each channel (``(log_time u64, offset u64)``
pairs, one ``np.frombuffer``), checks the Message record headers they point at (opcode, length,
channel, log time, CDR header: one vectorised gather), and gathers the fixed-length payloads with
one ``np.take`` over a one-byte-stride view of the decompressed group, straight into the
preallocated output. No Python object is made per message (except events, which are JSON).

The dtypes come from the ros2msg schema text stored in the file (:func:`schemas.parse_msg`), so
field names are the message fields (``u_cmd_a``, ``dac_counts``, ...) and arrays are subarrays.
A damaged file gives the readable part and a warning for every loss; only a file that is not an
MCAP log at all raises :class:`~dob_hil.errors.LogReadError`.
"""

from __future__ import annotations

import contextlib
import json
import mmap
import threading
import zlib
from collections import deque
from collections.abc import Iterable, Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np
import numpy.typing as npt
import zstandard

from dob_hil.errors import LogReadError
from dob_hil.log import mcap_scan
from dob_hil.log.blocks import block_counts, expand_runs, first_record_offsets
from dob_hil.log.blocks import gather as _gather
from dob_hil.log.mcap_scan import ChunkRef, FileMap
from dob_hil.log.schemas import (
    BLOCK_SUFFIX,
    CDR_HEADER_U32,
    MESSAGE_LAYOUTS,
    MESSAGE_RECORD_OVERHEAD,
    TOPIC_CAN,
    TOPIC_CAN_FD,
    TOPIC_EVENT,
    TOPIC_SAMPLE,
    TOPIC_TRUTH,
    WRITTEN_KEYS,
    Field,
    LogLayout,
    SchemaError,
    block_stride,
    channel_specs,
    decode_event_cdr,
    msg_dtype,
    parse_block_msg,
    parse_msg,
)

try:  # lz4 is optional: only needed for logs written with compression="lz4"
    import lz4.frame as _lz4_frame  # type: ignore[import-untyped,unused-ignore]
except ImportError:  # pragma: no cover
    _lz4_frame = None

GROUP_BYTES: Final = 8 << 20
# What a chunk may claim, decompressed: at most MAX_CHUNK_BYTES, and at most MAX_CHUNK_RATIO times
# its compressed size (at least MIN_CHUNK_CLAIM_BYTES): a crafted 37 KB file cannot make the reader
# allocate gigabytes (a zstd frame of zeros expands 32000-fold). The writer's chunks are 256 KiB
# and compress 2-3 fold.
MAX_CHUNK_BYTES: Final = 64 << 20
MAX_CHUNK_RATIO: Final = 256
MIN_CHUNK_CLAIM_BYTES: Final = 1 << 20
READ_AHEAD_BYTES: Final = 32 << 20  # decompressed bytes in flight at most (and one chunk)
FIXED_TOPICS: Final = (TOPIC_SAMPLE, TOPIC_CAN, TOPIC_CAN_FD, TOPIC_TRUTH)
_HEADER_DTYPE: Final = np.dtype(
    {
        "names": ["op", "length", "channel", "log_time", "cdr"],
        "formats": ["u1", "<u8", "<u2", "<u8", "<u4"],
        "offsets": [0, 1, 9, 15, 31],
        "itemsize": 35,
    }
)
_JSON_HEADER_DTYPE: Final = np.dtype(
    {"names": ["op", "length", "channel", "log_time"], "formats": ["u1", "<u8", "<u2", "<u8"],
     "offsets": [0, 1, 9, 15], "itemsize": 31}
)  # fmt: skip

StructArray = npt.NDArray[np.void]
# the writer's summary key of each channel's records written
_WRITTEN_KEY_OF_TOPIC: Final = {s.topic: WRITTEN_KEYS[s.key] for s in channel_specs(LogLayout(1, 1, 1, 1))}

_READ_THREADS: Final = 2  # chunk decompression workers (zstd and crc32 release the GIL)
_READ_AHEAD: Final = 32  # chunks in flight at most, to bound memory


@dataclass(slots=True)
class LogData:
    """A log read back. Arrays are in file order (the order the loop wrote them)."""

    samples: StructArray  # /dob_hil/sample, fields as in dob_hil/msg/Sample
    frames: StructArray  # /dob_hil/can (classic frames and FD frames of up to 8 bytes)
    fd_frames: StructArray  # /dob_hil/can_fd (CAN FD frames of 9..64 bytes)
    truth: StructArray  # /dob_hil/truth
    events: list[dict[str, Any]]
    metadata: dict[str, dict[str, str]]
    attachments: dict[str, bytes]
    layout: LogLayout
    warnings: list[str] = field(default_factory=list)
    complete: bool = False  # closed cleanly, nothing lost


@dataclass(slots=True)
class _Fixed:
    """Output of one fixed-size CDR channel."""

    channel_id: int
    topic: str
    dtype: np.dtype[np.void]  # the output: the message's fields, or the subset asked for
    payload_length: int  # CDR header + body
    out: StructArray
    filled: int = 0
    record_dtype: np.dtype[np.void] | None = None  # the message layout, where dtype is a subset
    counted: int = 0  # messages the chunks' indexes count (a block channel: records, -1 until asked)
    stride: int = 0  # a block channel: bytes per record in a block (0: one record per message)

    def reserve(self, extra: int) -> None:
        if self.filled + extra > len(self.out):
            grown = np.zeros(max(self.filled + extra, 2 * len(self.out)), dtype=self.dtype)
            grown[: self.filled] = self.out[: self.filled]
            self.out = grown


class _Group:
    """The decompressed records of consecutive chunks, back to back in one buffer."""

    def __init__(self) -> None:
        self.chunks: list[ChunkRef] = []
        self.datas: list[bytes] = []
        self.bases: list[int] = []
        self.size = 0
        self.buf = b""

    def add(self, chunk: ChunkRef, data: bytes) -> None:
        self.chunks.append(chunk)
        self.datas.append(data)
        self.bases.append(self.size)
        self.size += len(data)

    def seal(self) -> None:
        self.buf = self.datas[0] if len(self.datas) == 1 else b"".join(self.datas)


def map_log(path: Path) -> mmap.mmap:
    """The log file mapped read-only; LogReadError for an empty or unreadable file."""
    try:
        with path.open("rb") as f:
            if f.seek(0, 2) == 0:
                raise LogReadError(f"{path}: empty file, not an MCAP log")
            return mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    except OSError as exc:
        raise LogReadError(f"{path}: cannot read: {exc}") from exc


def read_log(
    path: Path | str,
    *,
    topics: Iterable[str] | None = None,
    fields: Mapping[str, Iterable[str]] | None = None,
    verify_crc: bool = True,
    log_time_window_ns: tuple[int, int] | None = None,
) -> LogData:
    """Read a dob_hil MCAP log; ``topics`` limits which channels are decoded (all by default).

    ``log_time_window_ns`` (first, last log time) reads only the chunks whose declared log times
    overlap that window (an indexed read: the rest of the file is never decompressed), so a
    stretch of a log of any length is read in memory bounded by the stretch; the arrays hold every
    message of those chunks, which may reach a chunk beyond either end of the window.

    ``fields`` maps a fixed-size topic to the message fields to keep (all by default): the
    arrays then hold only those, so an hour-long log fits in memory for an analysis that needs
    a few fields. A field the message does not have raises :class:`LogReadError`.
    """
    path = Path(path)
    mm = map_log(path)
    try:
        keep = None if fields is None else {topic: tuple(names) for topic, names in fields.items()}
        reader = _Reader(mm, str(path), None if topics is None else set(topics), verify_crc, keep)
        return reader.read(log_time_window_ns)
    finally:
        mm.close()


def iter_channel(
    path: Path | str, topic: str, fields: Iterable[str] | None = None, *, verify_crc: bool = True
) -> Iterator[StructArray]:
    """The messages of one fixed-size channel, block by block (one block per ~8 MiB of chunks).

    Memory stays bounded whatever the log's length: only one group of chunks and its block are
    held at a time. Warnings about damage are not reported here (read them with
    :func:`read_log` restricted to the events, which maps the whole file cheaply).
    """
    path = Path(path)
    mm = map_log(path)
    try:
        keep = None if fields is None else {topic: tuple(fields)}
        reader = _Reader(mm, str(path), {topic}, verify_crc, keep)
        reader._learn_channels()
        layout = reader._layout()
        fixed, _ = reader._outputs(layout, preallocate=False)
        for group in reader._groups():
            table = reader._table(group)
            for out in fixed.values():
                out.out, out.filled = out.out[:0], 0  # a fresh array per block
                reader._gather_fixed(group, table, out)
                if out.filled:
                    yield out.out[: out.filled]
            reader._release(group)
    finally:
        mm.close()


class _Reader:
    def __init__(
        self,
        mm: mmap.mmap,
        path: str,
        topics: set[str] | None,
        verify_crc: bool,
        fields: dict[str, tuple[str, ...]] | None = None,
    ) -> None:
        self.mm = mm
        self.fields = fields or {}
        self.path = path
        self.topics = topics
        self.verify_crc = verify_crc
        self.fmap: FileMap = mcap_scan.scan(mm, path)
        self.warnings = self.fmap.warnings
        self.dctx = zstandard.ZstdDecompressor()
        self.first_data: tuple[ChunkRef, bytes] | None = None
        self.event_json = False

    # ------------------------------------------------------------------ top level
    def read(self, log_time_window_ns: tuple[int, int] | None = None) -> LogData:
        fmap = self.fmap
        self._learn_channels()
        layout = self._layout()
        if log_time_window_ns is not None:  # after the channels: a summary-less log finds them in chunk 1
            first_ns, last_ns = log_time_window_ns
            # (a block-layout chunk declares its last record's time as its end: see blocks.py)
            fmap.chunks = [c for c in fmap.chunks if c.end_time_ns >= first_ns and c.start_time_ns <= last_ns]
        fixed, event_channel = self._outputs(layout)
        events: list[dict[str, Any]] = []
        for group in self._groups():
            table = self._table(group)
            for out in fixed.values():
                self._gather_fixed(group, table, out)
            if event_channel is not None:
                self._gather_events(group, table, event_channel, events)
            self._release(group)
        by_topic = {out.topic: out.out[: out.filled] for out in fixed.values()}
        empty = {spec.topic: np.zeros(0, dtype=_spec_dtype(spec.fields)) for spec in _fixed_specs(layout)}
        return LogData(
            samples=by_topic.get(TOPIC_SAMPLE, empty[TOPIC_SAMPLE]),
            frames=by_topic.get(TOPIC_CAN, empty[TOPIC_CAN]),
            fd_frames=by_topic.get(TOPIC_CAN_FD, empty[TOPIC_CAN_FD]),
            truth=by_topic.get(TOPIC_TRUTH, empty[TOPIC_TRUTH]),
            events=events,
            metadata=fmap.metadata,
            attachments=fmap.attachments,
            layout=layout,
            warnings=self.warnings,
            complete=fmap.complete and not self.warnings,
        )

    # ------------------------------------------------------------------ channels and layout
    def _learn_channels(self) -> None:
        """Schemas and channels: outside chunks, in the summary, else in the first readable chunk."""
        if self.fmap.channels:
            return
        for chunk in self.fmap.chunks:
            data = self._decompress(chunk, warn=False)
            if data is None:
                continue
            walk = mcap_scan.walk_chunk(data)
            for schema in walk.schemas:
                self.fmap.schemas[schema.id] = schema
            for channel in walk.channel_records:
                self.fmap.channels[channel.id] = channel
            self.first_data = (chunk, data)
            return

    def _layout(self) -> LogLayout:
        by_topic = {c.topic: c for c in self.fmap.channels.values()}
        fields: dict[str, dict[str, int]] = {}
        for topic in (TOPIC_SAMPLE, TOPIC_TRUTH):
            channel = by_topic.get(topic)
            schema = self.fmap.schemas.get(channel.schema_id) if channel is not None else None
            if schema is None:
                continue
            try:
                fields[topic] = {f.name: f.n_values for f in record_fields(schema)}
            except SchemaError as exc:
                self.warnings.append(f"{topic}: schema {schema.name!r} unusable: {exc}")
        sample, truth = fields.get(TOPIC_SAMPLE), fields.get(TOPIC_TRUTH)
        fmt = self.fmap.metadata.get("log_format", {})
        try:
            if sample is not None and truth is not None:
                return LogLayout(sample["x_ref"], sample["u_fb"], sample["counts"], truth["state"])
            layout = LogLayout(
                int(fmt["n_states"]), int(fmt["n_inputs"]), int(fmt["n_outputs"]), int(fmt["n_plant_states"])
            )
        except (KeyError, ValueError, SchemaError) as exc:
            raise LogReadError(
                f"{self.path}: not a dob_hil log (no {TOPIC_SAMPLE}/{TOPIC_TRUTH} schemas and no "
                f"log_format metadata: {exc})"
            ) from exc
        if self.fmap.chunks:
            self.warnings.append(
                "channel schemas not found: decoding with the layout of the log_format metadata"
            )
        try:
            ids = json.loads(fmt.get("channels", "{}"))
        except ValueError:
            ids = {}
        message_layout = fmt.get("message_layout", "samples")
        if message_layout not in MESSAGE_LAYOUTS:
            self.warnings.append(f"log_format: unknown message layout {message_layout!r}; read as samples")
            message_layout = "samples"
        specs = {spec.topic: spec for spec in channel_specs(layout, message_layout)}
        for key, topic in ids.items() if isinstance(ids, dict) else ():
            spec = specs.get(str(topic))
            if spec is not None and str(key).isdigit():
                self.fmap.schemas.setdefault(
                    int(key),
                    mcap_scan.SchemaRecord(
                        int(key), spec.schema_name, spec.schema_encoding, spec.schema_data()
                    ),
                )
                self.fmap.channels.setdefault(
                    int(key), mcap_scan.ChannelRecord(int(key), int(key), spec.topic, spec.message_encoding)
                )
        return layout

    def _outputs(self, layout: LogLayout, preallocate: bool = True) -> tuple[dict[int, _Fixed], int | None]:
        """The outputs of the channels read (arrays of the indexed message counts, or empty
        ones with ``preallocate`` False; :meth:`counted` gives the count) and the event channel."""
        counts: dict[int, int] = {}
        for chunk in self.fmap.chunks:
            for channel_id, (_, count) in chunk.indexes.items():
                counts[channel_id] = counts.get(channel_id, 0) + count
        fixed: dict[int, _Fixed] = {}
        event_channel: int | None = None
        for channel in self.fmap.channels.values():
            if self.topics is not None and channel.topic not in self.topics:
                continue
            if channel.topic == TOPIC_EVENT and channel.message_encoding in ("json", "cdr"):
                event_channel = channel.id
                self.event_json = channel.message_encoding == "json"  # format 1 logs
                continue
            if channel.topic not in FIXED_TOPICS:
                continue
            schema = self.fmap.schemas.get(channel.schema_id)
            if schema is None or schema.encoding != "ros2msg" or channel.message_encoding != "cdr":
                self.warnings.append(f"{channel.topic}: no ros2msg/cdr schema; channel skipped")
                continue
            block = schema.name.endswith(BLOCK_SUFFIX)
            try:
                fields = record_fields(schema)
                dtype = msg_dtype(fields)
            except SchemaError as exc:
                self.warnings.append(
                    f"{channel.topic}: schema {schema.name!r} unusable ({exc}); channel skipped"
                )
                continue
            stride = block_stride(fields) if block else 0
            if block:  # counted when needed (a log cut short is decompressed once more for it)
                n = self._block_records(channel.topic, stride) if preallocate else -1
            else:
                n = counts.get(channel.id, 0)
            size = max(n, 0) if preallocate else 0
            keep = self.fields.get(channel.topic)
            if keep is None:
                fixed[channel.id] = _Fixed(
                    channel.id, channel.topic, dtype, 4 + dtype.itemsize, np.zeros(size, dtype), counted=n,
                    stride=stride,
                )  # fmt: skip
                continue
            assert dtype.fields is not None
            unknown = [name for name in keep if name not in dtype.fields]
            if unknown:
                raise LogReadError(
                    f"{self.path}: {channel.topic} has no field {unknown[0]!r}; "
                    f"fields: {', '.join(dtype.fields)}"
                )
            subset = np.dtype([(name, dtype.fields[name][0]) for name in keep])
            fixed[channel.id] = _Fixed(
                channel.id, channel.topic, subset, 4 + dtype.itemsize, np.zeros(size, subset), 0, dtype, n,
                stride,
            )  # fmt: skip
        return fixed, event_channel

    def block_channels(self) -> dict[int, int]:
        """The channels whose messages are blocks of records (the block layout): id -> record stride."""
        strides = {}
        for c in self.fmap.channels.values():
            schema = self.fmap.schemas.get(c.schema_id)
            if schema is not None and schema.name.endswith(BLOCK_SUFFIX):
                with contextlib.suppress(SchemaError):  # an unusable schema: its channel is skipped
                    strides[c.id] = block_stride(record_fields(schema))
        return strides

    def counted(self, out: _Fixed) -> int:
        """Records of ``out``'s channel the indexes count (a block channel's, counted now if not yet)."""
        if out.counted < 0:
            out.counted = self._block_records(out.topic, out.stride)
        return out.counted

    def _block_records(self, topic: str, stride: int) -> int:
        """Records of a block channel: the writer's count for a log it closed (its summary), else
        those of every readable block (each chunk decompressed once more: a log cut short only).
        Never more than the chunks the reader would decompress can hold (a crafted summary)."""
        sizes = [c.uncompressed_size for c in self.fmap.chunks]
        limits = [chunk_claim_limit(c.data_length) for c in self.fmap.chunks]
        most = sum(size for size, limit in zip(sizes, limits, strict=True) if size <= limit) // stride
        written = self.fmap.metadata.get("summary", {}).get(_WRITTEN_KEY_OF_TOPIC.get(topic, ""))
        if self.fmap.complete and written is not None and written.isdigit():
            return min(int(written), most)
        channel_ids = {c.id for c in self.fmap.channels.values() if c.topic == topic}
        total = 0
        for chunk in self.fmap.chunks:
            if not any(chunk.indexes.get(cid, (0, 0))[1] for cid in channel_ids):
                continue
            data = self._decompress(chunk, warn=False)
            if data is None:
                continue
            walk = mcap_scan.walk_chunk(data)
            mine = [i for i, cid in enumerate(walk.channels) if cid in channel_ids]
            counts = block_counts(
                data,
                np.asarray([walk.offsets[i] for i in mine], dtype=np.int64),
                np.asarray([walk.lengths[i] for i in mine], dtype=np.int64),
                stride,
            )
            total += int(counts[counts > 0].sum())
        return min(total, most)

    # ------------------------------------------------------------------ chunks
    def _decompress(
        self, chunk: ChunkRef, warn: bool = True, dctx: zstandard.ZstdDecompressor | None = None
    ) -> bytes | None:
        if self.first_data is not None and self.first_data[0] is chunk:
            return self.first_data[1]
        where = f"chunk at byte {chunk.offset}"
        if chunk.uncompressed_size > chunk_claim_limit(chunk.data_length):
            if warn:
                self.warnings.append(
                    f"{where}: implausible uncompressed size {chunk.uncompressed_size} for "
                    f"{chunk.data_length} compressed bytes; chunk skipped"
                )
            return None
        raw = self.mm[chunk.data_offset : chunk.data_offset + chunk.data_length]
        try:
            if chunk.compression == "zstd":
                declared = zstandard.frame_content_size(raw)
                if declared > chunk.uncompressed_size:
                    raise ValueError(f"its zstd frame declares {declared} bytes")
                # without a declared size, max_output_size bounds what is allocated
                data = (dctx or self.dctx).decompress(raw, max_output_size=chunk.uncompressed_size)
            elif chunk.compression == "":
                data = raw
            elif chunk.compression == "lz4" and _lz4_frame is not None:
                data = _lz4_frame.LZ4FrameDecompressor().decompress(raw, max_length=chunk.uncompressed_size)
            else:
                if warn:
                    self.warnings.append(
                        f"{where}: unsupported compression {chunk.compression!r}; chunk skipped"
                    )
                return None
        except (zstandard.ZstdError, RuntimeError, ValueError, MemoryError) as exc:
            if warn:
                self.warnings.append(f"{where}: bad compressed data ({exc}); chunk skipped")
            return None
        if len(data) != chunk.uncompressed_size:
            if warn:
                self.warnings.append(
                    f"{where}: decompressed to {len(data)} bytes, "
                    f"expected {chunk.uncompressed_size}; chunk skipped"
                )
            return None
        if self.verify_crc and chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
            if warn:
                self.warnings.append(f"{where}: CRC mismatch; chunk skipped")
            return None
        return bytes(data)

    def _decompressed(self) -> Iterator[tuple[ChunkRef, bytes | None]]:
        """Every chunk decompressed and checked, in file order, by a small thread pool.

        zstd and crc32 release the GIL, so a second core nearly halves the read time. At most
        ``_READ_AHEAD`` chunks and ``READ_AHEAD_BYTES`` (decompressed, as the chunks declare them,
        each already bounded by :func:`chunk_claim_limit`) are in flight, so memory stays bounded
        for any file, hostile ones included.
        """
        chunks = self.fmap.chunks
        if len(chunks) < 4:
            for chunk in chunks:
                yield chunk, self._decompress(chunk)
            return
        local = threading.local()

        def work(chunk: ChunkRef) -> bytes | None:
            dctx = getattr(local, "dctx", None)
            if dctx is None:
                dctx = local.dctx = zstandard.ZstdDecompressor()
            return self._decompress(chunk, dctx=dctx)

        with ThreadPoolExecutor(max_workers=_READ_THREADS) as pool:
            pending: deque[tuple[ChunkRef, Future[bytes | None]]] = deque()
            in_flight = 0
            for chunk in chunks:
                claim = min(chunk.uncompressed_size, MAX_CHUNK_BYTES)
                while pending and (len(pending) >= _READ_AHEAD or in_flight + claim > READ_AHEAD_BYTES):
                    done, fut = pending.popleft()
                    in_flight -= min(done.uncompressed_size, MAX_CHUNK_BYTES)
                    yield done, fut.result()
                pending.append((chunk, pool.submit(work, chunk)))
                in_flight += claim
            while pending:
                done, fut = pending.popleft()
                yield done, fut.result()

    def _groups(self) -> Iterator[_Group]:
        group = _Group()
        for chunk, data in self._decompressed():
            if data is None:
                continue
            group.add(chunk, data)
            if group.size >= GROUP_BYTES:
                group.seal()
                yield group
                group = _Group()
        if group.chunks:
            group.seal()
            yield group

    def _release(self, group: _Group) -> None:
        """Drop the group's file pages from this process (the page cache keeps them)."""
        start = group.chunks[0].offset // mmap.PAGESIZE * mmap.PAGESIZE
        end = group.chunks[-1].index_end
        if end > start and hasattr(self.mm, "madvise"):
            with contextlib.suppress(OSError, ValueError):
                self.mm.madvise(mmap.MADV_DONTNEED, start, end - start)

    # ------------------------------------------------------------------ messages
    def _table(self, group: _Group) -> _Table:
        """Every Message record of the group, from the message indexes, checked against the records.

        A chunk's index is trusted only if its entries point at Message records of the right
        channel and log time that tile the chunk exactly (each record ends where the next begins,
        the last at the chunk's end, and only non-message records precede the first). Otherwise
        the chunk is re-indexed by walking its records.
        """
        n_chunks = len(group.chunks)
        sizes = np.asarray([len(d) for d in group.datas], dtype=np.int64)
        bases = np.asarray(group.bases, dtype=np.int64)
        raw: list[bytes] = []
        channel_ids: list[int] = []
        counts: list[int] = []
        chunk_ids: list[int] = []
        for i, chunk in enumerate(group.chunks):
            for channel_id, (pairs_offset, count) in chunk.indexes.items():
                if count:
                    raw.append(self.mm[pairs_offset : pairs_offset + 16 * count])
                    channel_ids.append(channel_id)
                    counts.append(count)
                    chunk_ids.append(i)
        pairs = np.frombuffer(b"".join(raw), dtype="<u8").reshape(-1, 2)
        channel_of = np.repeat(np.asarray(channel_ids, dtype=np.int64), counts)
        chunk_of = np.repeat(np.asarray(chunk_ids, dtype=np.int64), counts)
        size_of = sizes[chunk_of].astype(np.uint64)
        ok = (pairs[:, 1] < size_of) & (pairs[:, 1] + np.uint64(MESSAGE_RECORD_OVERHEAD) <= size_of)
        local = np.where(ok, pairs[:, 1], 0).astype(np.int64)
        offsets = local + bases[chunk_of]
        order = np.argsort(offsets, kind="stable")
        offsets, local, chunk_of, channel_of = (
            offsets[order],
            local[order],
            chunk_of[order],
            channel_of[order],
        )
        ok = ok[order]
        log_times = pairs[order, 0]
        heads = _gather(group.buf, _JSON_HEADER_DTYPE, np.where(ok, offsets, 0))
        lengths = np.minimum(heads["length"], np.uint64(1 << 40)).astype(np.int64)
        ends = local + 9 + lengths
        ok &= (
            (heads["op"] == mcap_scan.OP_MESSAGE)
            & (heads["channel"] == channel_of)
            & (heads["log_time"] == log_times)
            & (lengths >= MESSAGE_RECORD_OVERHEAD - 9)
            & (ends <= sizes[chunk_of])
        )
        bad = np.zeros(n_chunks, dtype=bool)
        bad[chunk_of[~ok]] = True
        n = len(offsets)
        is_last = np.ones(n, dtype=bool)
        if n > 1:
            same = chunk_of[1:] == chunk_of[:-1]
            is_last[:-1] = ~same
            bad[chunk_of[:-1][same & (ends[:-1] != local[1:])]] = True
        bad[chunk_of[is_last & (ends != sizes[chunk_of])]] = True
        first_local = sizes.copy()  # a chunk without indexed messages must hold no message at all
        is_first = np.ones(n, dtype=bool)
        is_first[1:] = is_last[:-1]
        first_local[chunk_of[is_first]] = local[is_first]
        for i in np.flatnonzero(~bad & (first_local > 0)).tolist():
            prefix = mcap_scan.walk_chunk(group.datas[i], 0, int(first_local[i]))
            bad[i] = bool(prefix.offsets or prefix.problem)
        if not bad.any():
            return _Table(offsets, channel_of, lengths)
        keep = ~bad[chunk_of]
        parts = [(offsets[keep], channel_of[keep], lengths[keep])]
        for i in np.flatnonzero(bad).tolist():
            chunk = group.chunks[i]
            if chunk.indexes:
                self.warnings.append(
                    f"chunk at byte {chunk.offset}: its message index is damaged; re-indexed from its records"
                )
            walk = mcap_scan.walk_chunk(group.datas[i])
            if walk.problem:
                self.warnings.append(
                    f"chunk at byte {chunk.offset}: {walk.problem}; its later messages are lost"
                )
            parts.append(
                (
                    np.asarray(walk.offsets, dtype=np.int64) + bases[i],
                    np.asarray(walk.channels, dtype=np.int64),
                    np.asarray(walk.lengths, dtype=np.int64),
                )
            )
        offsets = np.concatenate([p[0] for p in parts])
        order = np.argsort(offsets, kind="stable")
        return _Table(
            offsets[order],
            np.concatenate([p[1] for p in parts])[order],
            np.concatenate([p[2] for p in parts])[order],
        )

    def _gather_fixed(self, group: _Group, table: _Table, out: _Fixed) -> None:
        select = table.channels == out.channel_id
        offsets = table.offsets[select]
        if len(offsets) == 0:
            return
        if out.stride:
            offsets = self._block_rows(group, offsets, table.lengths[select], out)
            if len(offsets) == 0:
                return
        else:
            offsets = self._checked_messages(group, offsets, table.lengths[select], out)
        out.reserve(len(offsets))
        record = out.record_dtype or out.dtype
        void = np.dtype((np.void, record.itemsize))
        # Raw void items gather ~5x faster than structured ones (and np.take(out=) copies the view).
        rows = _gather(group.buf, void, offsets)
        end = out.filled + len(offsets)
        if out.record_dtype is None:
            out.out.view(void)[out.filled : end] = rows
        else:  # a subset of the fields: copied field by field from this group's records
            full = rows.view(record)
            assert out.dtype.names is not None
            for name in out.dtype.names:
                out.out[name][out.filled : end] = full[name]
        out.filled = end

    def _block_rows(
        self, group: _Group, offsets: npt.NDArray[np.int64], lengths: npt.NDArray[np.int64], out: _Fixed
    ) -> npt.NDArray[np.int64]:
        """Where each record of the channel's block messages starts (the block layout): a block
        whose length does not match its count, or not CDR, is skipped with a warning."""
        counts = block_counts(group.buf, offsets, lengths, out.stride)
        good = counts >= 0
        if not good.all():
            self.warnings.append(
                f"{out.topic}: {int((~good).sum())} blocks of the wrong length or encoding skipped"
            )
            offsets, counts = offsets[good], counts[good]
        return expand_runs(first_record_offsets(offsets), counts, out.stride)

    def _checked_messages(
        self, group: _Group, offsets: npt.NDArray[np.int64], lengths: npt.NDArray[np.int64], out: _Fixed
    ) -> npt.NDArray[np.int64]:
        """Where the body of each of the channel's messages starts (one record per message)."""
        good = lengths == MESSAGE_RECORD_OVERHEAD - 9 + out.payload_length
        good &= _gather(group.buf, np.dtype("<u4"), np.where(good, offsets + MESSAGE_RECORD_OVERHEAD, 0)) == (
            CDR_HEADER_U32
        )
        if not good.all():
            self.warnings.append(
                f"{out.topic}: {int((~good).sum())} messages of the wrong length or encoding skipped"
            )
            offsets = offsets[good]
        return offsets + MESSAGE_RECORD_OVERHEAD + 4

    def _gather_events(
        self, group: _Group, table: _Table, channel_id: int, events: list[dict[str, Any]]
    ) -> None:
        select = table.channels == channel_id
        buf = group.buf
        for offset, length in zip(
            table.offsets[select].tolist(), table.lengths[select].tolist(), strict=True
        ):
            payload = buf[offset + MESSAGE_RECORD_OVERHEAD : offset + 9 + length]
            try:
                event = json.loads(payload) if self.event_json else decode_event_cdr(payload)
            except (ValueError, RecursionError) as exc:
                self.warnings.append(f"{TOPIC_EVENT}: a message is not an event ({exc}); skipped")
                continue
            if isinstance(event, dict):
                events.append(event)


def record_fields(schema: mcap_scan.SchemaRecord) -> tuple[Field, ...]:
    """The fields of one record of a channel's schema: the message's own, or for a block schema
    (its name ends in ``Block``) those of the records it holds. SchemaError if unusable."""
    text = schema.data.decode(errors="replace")
    return parse_block_msg(text) if schema.name.endswith(BLOCK_SUFFIX) else parse_msg(text)


def chunk_claim_limit(compressed_bytes: int) -> int:
    """The largest uncompressed size a chunk of ``compressed_bytes`` may declare (see MAX_CHUNK_*)."""
    return min(MAX_CHUNK_BYTES, max(MIN_CHUNK_CLAIM_BYTES, MAX_CHUNK_RATIO * compressed_bytes))


@dataclass(slots=True)
class _Table:
    """The Message records of a group: global offsets (ascending), channel ids, record lengths."""

    offsets: npt.NDArray[np.int64]
    channels: npt.NDArray[np.int64]
    lengths: npt.NDArray[np.int64]


def _fixed_specs(layout: LogLayout) -> list[Any]:
    return [spec for spec in channel_specs(layout) if spec.fields is not None]


def _spec_dtype(fields: Any) -> np.dtype[np.void]:
    return msg_dtype(fields)


__all__ = ["LogData", "iter_channel", "read_log"]
