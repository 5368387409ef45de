"""python-can speaks dob_hil's MCAP: a message writer and reader registered as python-can plugins.

With dob_hil installed, python-can's own tools handle ``.mcap`` files (entry points
``can.io.message_writer`` and ``can.io.message_reader``)::

    python -m can.logger -i socketcan -c can0 -f capture.mcap   # record any bus
    python -m can.player capture.mcap -i socketcan -c vcan0      # play it back
    python -m can.logconvert run.mcap run.blf                    # a dob_hil run log to BLF
    can.Logger("x.mcap"), can.LogReader("x.mcap")                # from Python

A capture is an MCAP file with the same channels, schemas (ros2msg/CDR, so Foxglove plots every
field) and "log_format" metadata as a run log, so ``dob-hil export`` and Foxglove open it like
one; its "run" metadata says ``mode = "capture"``, and its log time is the frames' own timestamp
(python-can's epoch seconds, in ns), kept non-decreasing per channel (a frame stamped before its
predecessor is logged at the predecessor's time; its own timestamp stays in the message).

The reader yields every classic and FD frame of a capture or a run log in log-time order, with the
timestamp on the wall clock (:mod:`dob_hil.log.wallclock`), ``is_rx`` from the logged direction,
and, by default, without the received copies of our own transmitted frames that udp_multicast
echoes (``keep_own_echoes=True`` keeps them).
"""

from __future__ import annotations

import heapq
import struct
import time
from collections.abc import Iterator
from typing import Any, BinaryIO, cast

import can
from can.io.generic import BinaryIOMessageReader, BinaryIOMessageWriter
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from dob_hil import __version__
from dob_hil.errors import LogReadError
from dob_hil.log.blocks import payload_block_count
from dob_hil.log.metadata import log_format_metadata
from dob_hil.log.schemas import (
    BLOCK_HEAD_BYTES,
    BLOCK_SUFFIX,
    CAN_DATA_BYTES,
    CAN_FD_DATA_BYTES,
    CAN_FLAG_BRS,
    CAN_FLAG_ERROR,
    CAN_FLAG_ESI,
    CAN_FLAG_EXTENDED,
    CAN_FLAG_FD,
    CAN_FLAG_REMOTE,
    CAN_RX,
    CAN_TX,
    CDR_HEADER,
    TOPIC_CAN,
    TOPIC_CAN_FD,
    LogLayout,
    block_stride,
    can_fields,
    channel_specs,
    struct_body_format,
)
from dob_hil.log.wallclock import CAPTURE_MODE, wall_offset_ns
from dob_hil.log.writer import message_flags

_LAYOUT = LogLayout(1, 1, 1, 1)  # the sample/truth channels of a capture stay empty
_CAN_BODY = struct.Struct("<" + struct_body_format(can_fields(CAN_DATA_BYTES)))
_CAN_FD_BODY = struct.Struct("<" + struct_body_format(can_fields(CAN_FD_DATA_BYTES)))
CHUNK_BYTES = 256 * 1024
_U64 = struct.Struct("<Q")
# mcap's reader on damaged input: its own errors (EndOfFile, RecordLengthLimitExceeded, ...), and
# what a cut or crafted record makes Python raise (a length past the end, a missing channel, ...)
_DAMAGE = (
    McapError, ValueError, struct.error, EOFError, KeyError, IndexError, OverflowError, MemoryError, OSError,
)  # fmt: skip
_STRIDES = {
    TOPIC_CAN: block_stride(can_fields(CAN_DATA_BYTES)),
    TOPIC_CAN_FD: block_stride(can_fields(CAN_FD_DATA_BYTES)),
}


def _block_records(topic: str, payload: bytes) -> range:
    """Where each frame of a block message starts, after its CDR header (the block layout)."""
    stride = _STRIDES[topic]
    count = payload_block_count(payload, stride)
    if count < 0:
        raise ValueError(f"{topic}: a damaged block of {len(payload)} bytes")
    return range(BLOCK_HEAD_BYTES, BLOCK_HEAD_BYTES + count * stride, stride)


def _flags(msg: can.Message) -> int:
    """The loop's flags of a frame, with a capture's bit-rate switch and error state indicator."""
    return (
        message_flags(msg)
        | (CAN_FLAG_BRS if msg.bitrate_switch else 0)
        | (CAN_FLAG_ESI if msg.error_state_indicator else 0)
    )


class McapCanWriter(BinaryIOMessageWriter):
    """python-can message writer for ``.mcap`` (module docstring)."""

    def __init__(self, file: Any, append: bool = False, **kwargs: Any) -> None:
        if append:
            raise ValueError("MCAP captures cannot be appended to; write a new file")
        super().__init__(file, mode="wb")
        self._writer = Writer(
            cast(BinaryIO, self.file), chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD
        )
        self._writer.start(profile="ros2", library=f"dob_hil {__version__} (python-can plugin)")
        self._channels: dict[str, int] = {}
        for spec in channel_specs(_LAYOUT):
            schema_id = self._writer.register_schema(
                spec.schema_name, spec.schema_encoding, spec.schema_data()
            )
            self._channels[spec.topic] = self._writer.register_channel(
                spec.topic, spec.message_encoding, schema_id
            )
        self._last_log_ns = {TOPIC_CAN: 0, TOPIC_CAN_FD: 0}
        self._seq = 0
        self._start_wall_ns: int | None = None
        self._finished = False

    def on_message_received(self, msg: can.Message) -> None:
        ts_ns = round(msg.timestamp * 1e9) if msg.timestamp else time.time_ns()
        if self._start_wall_ns is None:
            self._start_wall_ns = ts_ns
        direction = CAN_RX if msg.is_rx else CAN_TX
        data = bytes(msg.data or b"")
        fd = len(data) > CAN_DATA_BYTES or msg.is_fd
        topic = TOPIC_CAN_FD if fd else TOPIC_CAN
        body = (_CAN_FD_BODY if fd else _CAN_BODY).pack(
            ts_ns, msg.arbitration_id, direction, msg.dlc, _flags(msg), data
        )
        log_ns = max(ts_ns, self._last_log_ns[topic])  # non-decreasing per channel
        self._last_log_ns[topic] = log_ns
        self._seq += 1
        self._writer.add_message(self._channels[topic], log_ns, CDR_HEADER + body, ts_ns, self._seq)

    def stop(self) -> None:
        if not self._finished:
            self._finished = True
            start = self._start_wall_ns if self._start_wall_ns is not None else time.time_ns()
            self._writer.add_metadata("log_format", log_format_metadata(_LAYOUT))
            self._writer.add_metadata(
                "run",
                {
                    "mode": CAPTURE_MODE,
                    "bus": "python-can capture",
                    "start_wall_time_ns": str(start),
                    "start_wall_time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(start / 1e9)),
                    "frames": str(self._seq),
                },
            )
            self._writer.finish()  # type: ignore[no-untyped-call]
        super().stop()


class McapCanReader(BinaryIOMessageReader):
    """python-can message reader for ``.mcap`` captures and dob_hil run logs (module docstring)."""

    def __init__(self, file: Any, keep_own_echoes: bool = False, **kwargs: Any) -> None:
        super().__init__(file, mode="rb")
        self.keep_own_echoes = keep_own_echoes

    def __iter__(self) -> Iterator[can.Message]:
        try:
            reader = make_reader(cast(BinaryIO, self.file))
            summary = reader.get_summary()
            metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            start = summary.statistics.message_start_time if summary and summary.statistics else None
            offset_ns = wall_offset_ns(metadata, start)
            tx_ids = set() if self.keep_own_echoes else self._tx_ids(reader)
            for msg in self._in_log_time_order(reader, offset_ns):
                if msg.is_rx and msg.arbitration_id in tx_ids:
                    continue  # a received copy of a frame we sent (udp_multicast's loopback)
                yield msg
        except _DAMAGE as exc:  # what mcap's reader raises on a damaged or crafted file
            raise LogReadError(f"{getattr(self.file, 'name', 'MCAP')}: not a readable MCAP: {exc}") from None
        finally:
            self.stop()

    def _in_log_time_order(self, reader: Any, offset_ns: int) -> Iterator[can.Message]:
        """Every frame in log-time order. Blocks come in the order of their first frames, and the
        blocks of the two CAN channels overlap in time, so a block's frames wait in a heap until
        a block starting later arrives (no frame of a block precedes its first one); they are
        ordered by their integer timestamp, then classic before FD (the block layout keeps no
        order between the two channels' frames of equal timestamp), then file order."""
        pending: list[tuple[int, int, int, can.Message]] = []
        n = 0
        for schema, channel, message in reader.iter_messages(
            topics=[TOPIC_CAN, TOPIC_CAN_FD], log_time_order=True
        ):
            if not schema.name.endswith(BLOCK_SUFFIX):
                yield self._decode(channel.topic, message.data, 0, offset_ns)
                continue
            while pending and pending[0][0] < message.log_time:
                yield heapq.heappop(pending)[3]
            fd = int(channel.topic == TOPIC_CAN_FD)
            for at in _block_records(channel.topic, message.data):
                (ts_ns,) = _U64.unpack_from(message.data, len(CDR_HEADER) + at)  # the record's log time
                n += 1
                heapq.heappush(
                    pending, (ts_ns, fd, n, self._decode(channel.topic, message.data, at, offset_ns))
                )
        while pending:
            yield heapq.heappop(pending)[3]

    def _tx_ids(self, reader: Any) -> set[int]:
        ids: set[int] = set()
        for schema, channel, message in reader.iter_messages(topics=[TOPIC_CAN, TOPIC_CAN_FD]):
            body = _CAN_FD_BODY if channel.topic == TOPIC_CAN_FD else _CAN_BODY
            block = schema.name.endswith(BLOCK_SUFFIX)
            for at in _block_records(channel.topic, message.data) if block else (0,):
                _ts, aid, direction, *_rest = body.unpack_from(message.data, len(CDR_HEADER) + at)
                if direction == CAN_TX:
                    ids.add(aid)
        return ids

    @staticmethod
    def _decode(topic: str, payload: bytes, at: int, offset_ns: int) -> can.Message:
        """The frame whose body starts ``at`` bytes after the CDR header of ``payload``."""
        body = _CAN_FD_BODY if topic == TOPIC_CAN_FD else _CAN_BODY
        ts_ns, aid, direction, dlc, flags, data = body.unpack_from(payload, len(CDR_HEADER) + at)
        remote = bool(flags & CAN_FLAG_REMOTE)
        length = 0 if remote else min(int(dlc), len(data))
        return can.Message(
            timestamp=(ts_ns + offset_ns) * 1e-9,
            arbitration_id=aid,
            is_extended_id=bool(flags & CAN_FLAG_EXTENDED),
            is_remote_frame=remote,
            is_error_frame=bool(flags & CAN_FLAG_ERROR),
            is_fd=bool(flags & CAN_FLAG_FD),
            bitrate_switch=bool(flags & CAN_FLAG_BRS),
            error_state_indicator=bool(flags & CAN_FLAG_ESI),
            is_rx=direction == CAN_RX,
            dlc=int(dlc),
            data=data[:length],
        )
