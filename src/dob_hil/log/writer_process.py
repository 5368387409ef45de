"""The log's writer process: reads the record stream on stdin, writes the MCAP file in bulk.

Run by :class:`~dob_hil.log.writer.LogWriter` as ``python -m dob_hil.log.writer_process``; the
record stream is described in :mod:`dob_hil.log.pipe`. The Message records arrive ready-made, so
this process only finds their boundaries (one header read per record) and hands whole runs of
them to :class:`~dob_hil.log.chunked_file.ChunkedFile`, which compresses and indexes each chunk.

Crash safety: a chunk is finished (and so reaches the kernel) when it holds ``chunk_size_bytes``
or has been open ``chunk_interval_ns``, whichever comes first; a SIGKILL of both processes loses
at most the open chunk and what was still in the pipe. On end of input without a ``close`` record
(the parent vanished) the file is finished with a summary saying so. SIGINT and SIGTERM are
ignored: the parent handles them and closes the log itself. SIGXFSZ is ignored, so a file size
limit is an error (EFBIG) reported to the parent like a full disk.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import sys
import time
from typing import Any, BinaryIO

from dob_hil.log import pipe
from dob_hil.log.chunked_file import ChunkedFile
from dob_hil.log.schemas import (
    OP_MESSAGE,
    WRITTEN_KEYS,
    LogLayout,
    channel_specs,
)

_READ_BYTES = 1 << 20
_HEAD = pipe.RECORD_HEAD


class LogFile:
    """The MCAP file and its chunking policy."""

    def __init__(self, config: dict[str, Any]) -> None:
        self.path = str(config["path"])
        layout = LogLayout(**config["layout"])
        self.chunk_size_bytes = int(config["chunk_size_bytes"])
        self.chunk_interval_ns = int(config["chunk_interval_ns"])
        message_layout = str(config.get("message_layout", "samples"))
        self.file = ChunkedFile(
            self.path,
            str(config["library"]),
            channel_specs(layout, message_layout),
            str(config["compression"]),
        )
        self.chunk_opened_ns = 0
        self.chunks = 0

    def messages(self, buf: bytearray, start: int, end: int, offsets: list[int]) -> None:
        if self.file.chunk_bytes == 0:
            self.chunk_opened_ns = time.monotonic_ns()
        self.file.add_messages(buf, start, end, offsets)
        if self.file.chunk_bytes >= self.chunk_size_bytes:
            self.finish_chunk()

    def room(self) -> int:
        """Bytes of records the open chunk takes before it is finished (at least 1)."""
        return max(1, self.chunk_size_bytes - self.file.chunk_bytes)

    def finish_chunk(self) -> None:
        if self.file.finish_chunk():
            self.chunks += 1

    def chunk_deadline_s(self) -> float | None:
        """Seconds until the open chunk must be finished, None if no chunk is open."""
        if self.file.chunk_bytes == 0:
            return None
        return max(0.0, (self.chunk_opened_ns + self.chunk_interval_ns - time.monotonic_ns()) * 1e-9)

    def written(self) -> dict[str, int]:
        """Records per kind in finished chunks (those that reached the file)."""
        counts = {key: int(self.file.record_counts.get(ch, 0)) for ch, key in WRITTEN_KEYS.items()}
        counts["chunks"] = self.chunks
        return counts

    def close(self, summary: dict[str, Any]) -> dict[str, int]:
        self.finish_chunk()
        written = self.written()
        data = {key: _text(value) for key, value in summary.items()}
        for key, value in written.items():
            data.setdefault(key, str(value))
        self.file.add_metadata("summary", data)
        self.file.finish()
        return written

    @property
    def finished(self) -> bool:
        return self.file.finished


def _text(value: object) -> str:
    return value if isinstance(value, str) else json.dumps(value, default=str)


class _Status:
    def __init__(self, stream: BinaryIO) -> None:
        self._stream = stream

    def send(self, **fields: Any) -> None:
        self._stream.write(json.dumps(fields, default=str).encode() + b"\n")
        self._stream.flush()


def _detach_from_control_loop() -> None:
    """Run as an ordinary process on every CPU, whatever the parent set (SCHED_FIFO, affinity)."""
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setaffinity(0, range(os.cpu_count() or 1))


def _control(log: LogFile | None, payload: bytes, status: _Status) -> tuple[LogFile | None, bool]:
    """Apply one control record; returns the log file and whether the log is closed."""
    obj, blob = pipe.split_control(payload)
    op = obj["op"]
    if op == pipe.OP_OPEN:
        try:
            return LogFile(obj), False
        except OSError as exc:
            raise RuntimeError(f"log file {obj.get('path')}: cannot open for writing: {exc}") from exc
    if log is None:
        raise RuntimeError(f"control record {op!r} before the open record")
    if op == pipe.OP_ATTACHMENT:
        log.file.add_attachment(
            int(obj["create_time"]),
            int(obj["log_time"]),
            str(obj["name"]),
            str(obj["media_type"]),
            blob or b"",
        )
    elif op == pipe.OP_METADATA:
        log.file.add_metadata(str(obj["name"]), {str(k): str(v) for k, v in obj["data"].items()})
    elif op == pipe.OP_SYNC:
        status.send(status=pipe.STATUS_READY)
    elif op == pipe.OP_CLOSE:
        written = log.close(dict(obj["summary"]))
        status.send(status=pipe.STATUS_CLOSED, written=written)
        return log, True
    else:
        raise RuntimeError(f"unknown control op {op!r}")
    return log, False


def run(fd_in: int, status: _Status) -> int:
    log: LogFile | None = None
    buf = bytearray()
    pos = 0
    closed = False
    unpack = _HEAD.unpack_from
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
            # every complete record: runs of Message records go to the chunk in one piece
            end = len(buf)
            run_start = pos
            offsets: list[int] = []
            room = log.room() if log is not None else 0  # bytes until the open chunk is full
            while end - pos >= 9:
                op, length = unpack(buf, pos)
                stop = pos + 9 + length
                if stop > end:
                    break
                if op == OP_MESSAGE:
                    offsets.append(pos)
                    pos = stop
                    if pos - run_start >= room:
                        if log is None:
                            raise RuntimeError("data record before the open record")
                        log.messages(buf, run_start, pos, offsets)  # finishes the chunk
                        offsets = []
                        run_start = pos
                        room = log.room()
                    continue
                if offsets:
                    if log is None:
                        raise RuntimeError("data record before the open record")
                    log.messages(buf, run_start, pos, offsets)
                    offsets = []
                if op != pipe.OP_CONTROL:
                    raise RuntimeError(f"unexpected record opcode 0x{op:02x} on the log pipe")
                log, closed = _control(log, bytes(buf[pos + 9 : stop]), status)
                pos = run_start = stop
                room = log.room() if log is not None else 0
                if closed:
                    break
            if offsets and not closed:
                if log is None:
                    raise RuntimeError("data record before the open record")
                log.messages(buf, run_start, pos, offsets)
            if pos > _READ_BYTES or pos == len(buf):
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
                if len(buf) - pos:
                    summary["incomplete_record_bytes"] = str(len(buf) - pos)
                written = log.close(summary)
                status.send(status=pipe.STATUS_CLOSED, written=written)
                closed = True
    except Exception as exc:  # report every failure to the parent, which raises it
        message = f"{type(exc).__name__}: {exc}"
        written_before = log.written() if log is not None else None
        if log is not None and not log.finished:
            try:  # leave a readable file if the disk still takes it
                log.file.chunk = bytearray()
                log.file.offsets = []
                log.close({"exit_reason": f"log writer error: {message}"})
            except Exception as close_exc:
                message += f" (and finishing the file failed: {type(close_exc).__name__}: {close_exc})"
            finally:
                log.file.close()
        status.send(status=pipe.STATUS_ERROR, message=message, written=written_before)
        return 1
    return 0


def main() -> int:
    # SIGINT and SIGTERM are the control loop's to handle (a Ctrl-C or a systemd stop reaches the
    # whole process group): the loop then stops the drive, writes its summary and closes the pipe,
    # and the end of the pipe is what finishes this file -- also when the loop dies. A writer that
    # must go regardless is stopped with SIGKILL.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    _detach_from_control_loop()
    return run(sys.stdin.fileno(), _Status(sys.stdout.buffer))


if __name__ == "__main__":
    sys.exit(main())
