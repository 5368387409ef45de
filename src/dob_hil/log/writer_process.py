"""The log's writer process: reads packed records on stdin, writes the MCAP file.

Run by :class:`~dob_hil.log.writer.LogWriter` as ``python -m dob_hil.log.writer_process``; the
record stream is described in :mod:`dob_hil.log.pipe`. All MCAP work (records, chunking, zstd)
happens here, so the control process only packs bytes.

Crash safety: the file is written through an unbuffered stream, and a chunk is finished (and so
reaches the kernel) when it holds ``chunk_size_bytes`` or has been open ``chunk_interval_ns``,
whichever comes first; a SIGKILL of both processes loses at most the open chunk and what was
still in the pipe. On end of input without a ``close`` record (the parent vanished) or on
SIGTERM the file is finished with a summary saying so. SIGINT is ignored: the parent handles
Ctrl-C and closes the log itself.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import sys
import time
from collections import Counter
from typing import Any, BinaryIO

from mcap.writer import CompressionType, Writer

from dob_hil.log import pipe
from dob_hil.log.schemas import (
    CH_CAN,
    CH_CAN_FD,
    CH_EVENT,
    CH_SAMPLE,
    CH_TRUTH,
    MESSAGE_RECORD_OVERHEAD,
    PIPE_HEADER,
    LogLayout,
    channel_specs,
)

_READ_BYTES = 1 << 20
_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
_WRITTEN_KEYS = {
    CH_SAMPLE: "samples_written",
    CH_CAN: "frames_written",
    CH_CAN_FD: "fd_frames_written",
    CH_TRUTH: "truth_written",
    CH_EVENT: "events_written",
}


class DirectStream:
    """A write-only file object without userspace buffering: every ``write`` reaches the kernel.

    mcap's Writer wraps raw files in a BufferedWriter; this object is not a RawIOBase, so it is
    used as is.
    """

    def __init__(self, fd: int) -> None:
        self._fd = fd
        self._pos = 0

    def write(self, data: bytes | bytearray | memoryview) -> int:
        view = memoryview(data)
        total = len(view)
        while view:
            written = os.write(self._fd, view)
            view = view[written:]
        self._pos += total
        return total

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        pass

    def close(self) -> None:
        os.close(self._fd)


class LogFile:
    """The MCAP file and its chunking policy."""

    def __init__(self, config: dict[str, Any]) -> None:
        self.path = str(config["path"])
        self.layout = LogLayout(**config["layout"])
        self.chunk_size_bytes = int(config["chunk_size_bytes"])
        self.chunk_interval_ns = int(config["chunk_interval_ns"])
        compression = _COMPRESSION[str(config["compression"])]
        fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644)
        self.stream = DirectStream(fd)
        # Chunks are finished here (chunk_bytes), never by the library's size check.
        self.writer = Writer(self.stream, chunk_size=1 << 62, compression=compression)  # type: ignore[arg-type]
        self.writer.start(profile="", library=str(config["library"]))
        self.sequence: Counter[int] = Counter()
        self.chunk_bytes = 0
        self.chunk_opened_ns = 0
        self.chunks = 0
        self.finished = False
        for spec in channel_specs(self.layout):
            schema_id = self.writer.register_schema(
                spec.schema_name, spec.schema_encoding, spec.schema_data()
            )
            channel_id = self.writer.register_channel(spec.topic, spec.message_encoding, schema_id)
            if channel_id != spec.key:
                raise RuntimeError(f"channel {spec.topic} got id {channel_id}, expected {spec.key}")

    def message(self, channel: int, log_time_ns: int, payload: bytes) -> None:
        if channel not in _WRITTEN_KEYS:
            raise ValueError(f"record for unknown channel {channel}")
        seq = self.sequence[channel]
        self.sequence[channel] = seq + 1
        if self.chunk_bytes == 0:
            self.chunk_opened_ns = time.monotonic_ns()
        self.writer.add_message(channel, log_time_ns, payload, log_time_ns, seq & 0xFFFFFFFF)
        self.chunk_bytes += MESSAGE_RECORD_OVERHEAD + len(payload)
        if self.chunk_bytes >= self.chunk_size_bytes:
            self.finish_chunk()

    def finish_chunk(self) -> None:
        if self.chunk_bytes:
            self.writer.flush()  # type: ignore[no-untyped-call]  # finishes the chunk and writes it with its message indexes
            self.chunk_bytes = 0
            self.chunks += 1

    def chunk_deadline_s(self) -> float | None:
        """Seconds until the open chunk must be finished, None if no chunk is open."""
        if self.chunk_bytes == 0:
            return None
        return max(0.0, (self.chunk_opened_ns + self.chunk_interval_ns - time.monotonic_ns()) * 1e-9)

    def written(self) -> dict[str, int]:
        counts = {key: self.sequence[ch] for ch, key in _WRITTEN_KEYS.items()}
        counts["chunks"] = self.chunks
        return counts

    def close(self, summary: dict[str, Any]) -> dict[str, int]:
        self.finish_chunk()
        written = self.written()
        data = {key: _text(value) for key, value in summary.items()}
        for key, value in written.items():
            data.setdefault(key, str(value))
        self.writer.add_metadata("summary", data)
        self.writer.finish()  # type: ignore[no-untyped-call]
        os.fsync(self.stream._fd)
        self.stream.close()
        self.finished = True
        return written


def _text(value: object) -> str:
    return value if isinstance(value, str) else json.dumps(value, default=str)


class _Status:
    def __init__(self, stream: BinaryIO) -> None:
        self._stream = stream

    def send(self, **fields: Any) -> None:
        self._stream.write(json.dumps(fields, default=str).encode() + b"\n")
        self._stream.flush()


def _detach_from_control_loop() -> None:
    """Run as an ordinary, lower-priority process on every CPU, whatever the parent set."""
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setaffinity(0, range(os.cpu_count() or 1))
    with contextlib.suppress(OSError):
        os.nice(5)


def run(fd_in: int, status: _Status) -> int:
    log: LogFile | None = None
    buf = bytearray()
    pos = 0
    closed = False
    try:
        poller = select.poll()
        poller.register(fd_in, select.POLLIN)
        eof = False
        while not closed:
            deadline_s = log.chunk_deadline_s() if log is not None else None
            if deadline_s is None or deadline_s > 0:
                timeout_ms = None if deadline_s is None else max(1, int(deadline_s * 1000) + 1)
                if poller.poll(timeout_ms):
                    data = os.read(fd_in, _READ_BYTES)
                    if data:
                        buf += data
                    else:
                        eof = True
            # parse every complete record
            end = len(buf)
            while end - pos >= PIPE_HEADER.size:
                channel, log_time_ns, length = PIPE_HEADER.unpack_from(buf, pos)
                start = pos + PIPE_HEADER.size
                if end - start < length:
                    break
                payload = bytes(buf[start : start + length])
                pos = start + length
                if channel != pipe.CH_CONTROL:
                    if log is None:
                        raise RuntimeError("data record before the open record")
                    log.message(channel, log_time_ns, payload)
                    continue
                obj, blob = pipe.split_control(payload)
                op = obj["op"]
                if op == pipe.OP_OPEN:
                    try:
                        log = LogFile(obj)
                    except OSError as exc:
                        raise RuntimeError(
                            f"log file {obj.get('path')}: cannot open for writing: {exc}"
                        ) from exc
                elif log is None:
                    raise RuntimeError(f"control record {op!r} before the open record")
                elif op == pipe.OP_ATTACHMENT:
                    log.writer.add_attachment(
                        int(obj["create_time"]),
                        int(obj["log_time"]),
                        str(obj["name"]),
                        str(obj["media_type"]),
                        blob or b"",
                    )
                elif op == pipe.OP_METADATA:
                    log.writer.add_metadata(
                        str(obj["name"]), {str(k): str(v) for k, v in obj["data"].items()}
                    )
                elif op == pipe.OP_SYNC:
                    status.send(status=pipe.STATUS_READY)
                elif op == pipe.OP_CLOSE:
                    written = log.close(dict(obj["summary"]))
                    status.send(status=pipe.STATUS_CLOSED, written=written)
                    closed = True
                    break
                else:
                    raise RuntimeError(f"unknown control op {op!r}")
            if pos > _READ_BYTES:
                del buf[:pos]
                pos = 0
            if log is not None and not closed:
                deadline_s = log.chunk_deadline_s()
                if deadline_s is not None and deadline_s <= 0:
                    log.finish_chunk()
            if eof and not closed:
                if log is None:
                    raise RuntimeError("the log pipe closed before the open record")
                summary = {"exit_reason": "parent vanished: the log pipe closed before close()"}
                if end - pos:
                    summary["incomplete_record_bytes"] = str(end - pos)
                written = log.close(summary)
                status.send(status=pipe.STATUS_CLOSED, written=written)
                closed = True
    except Exception as exc:  # report every failure to the parent, which raises it
        message = f"{type(exc).__name__}: {exc}"
        if log is not None and not log.finished:
            try:  # leave a readable file if the disk still takes it
                log.close({"exit_reason": f"log writer error: {message}"})
            except Exception as close_exc:
                message += f" (and finishing the file failed: {type(close_exc).__name__}: {close_exc})"
        status.send(status=pipe.STATUS_ERROR, message=message)
        return 1
    return 0


def main() -> int:
    # SIGINT and SIGTERM are the control loop's to handle (a Ctrl-C or a systemd stop reaches the
    # whole process group): the loop then stops the drive, writes its summary and closes the pipe,
    # and the end of the pipe is what finishes this file -- also when the loop dies. A writer that
    # must go regardless is stopped with SIGKILL.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _detach_from_control_loop()
    return run(sys.stdin.fileno(), _Status(sys.stdout.buffer))


if __name__ == "__main__":
    sys.exit(main())
