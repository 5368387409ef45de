"""LogWriter: the control-thread side of the log.

The control thread only packs each record with one precomputed :class:`struct.Struct` and
appends it to a local batch (a ``bytearray``). :meth:`LogWriter.flush` hands the batch to the
writer process through a non-blocking pipe; what the pipe does not take waits in a bounded
backlog, and when the backlog is full whole batches are dropped, counted, and reported by a
``log_overflow`` event as soon as there is room again. Nothing here ever blocks on the writer
process, except construction (waits for the process to open the file) and :meth:`close`.

Call every method from one thread (the control thread): the writer is not thread-safe.
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import json
import os
import select
import struct
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Final

import can

import dob_hil
from dob_hil.errors import LogWriteError
from dob_hil.log import pipe
from dob_hil.log.metadata import log_format_metadata, versions_metadata
from dob_hil.log.schemas import (
    CAN_DATA_BYTES,
    CAN_FD_DATA_BYTES,
    CAN_FLAG_ERROR,
    CAN_FLAG_EXTENDED,
    CAN_FLAG_FD,
    CAN_FLAG_REMOTE,
    CAN_RX,
    CAN_TX,
    CDR_HEADER_U32,
    CH_CAN,
    CH_CAN_FD,
    CH_EVENT,
    CH_SAMPLE,
    CH_TRUTH,
    EVENT_LEVELS,
    PIPE_HEADER,
    LogLayout,
    body_size,
    can_fields,
    record_struct,
    sample_fields,
    truth_fields,
)

DEFAULT_CHUNK_SIZE_BYTES: Final = 32 * 1024
DEFAULT_CHUNK_INTERVAL_NS: Final = 40_000_000
DEFAULT_MAX_BACKLOG_BYTES: Final = 64 * 1024 * 1024
# The control thread hands batches over in flush() (after the command is sent): about one sample
# in 130 pays for the pipe write (10-15 us), so the p99 cost per sample stays that of packing.
# batch_bytes is only a safety valve for a caller that never flushes. Worst loss at SIGKILL of
# the whole process group: the unflushed batch (<= 40 ms) plus the open chunk (<= 40 ms).
DEFAULT_BATCH_BYTES: Final = 256 * 1024
DEFAULT_FLUSH_BYTES: Final = 48 * 1024
DEFAULT_FLUSH_INTERVAL_NS: Final = 40_000_000
PIPE_CAPACITY_BYTES: Final = 1 << 20
_MEDIA_TYPES: Final = {".json": "application/json", ".toml": "application/toml", ".txt": "text/plain"}


@dataclass(frozen=True, slots=True)
class LogStats:
    """Counters of the control-thread side; ``written_records`` is known after close."""

    enqueued_records: int  # records handed to the pipe or waiting in the backlog
    enqueued_bytes: int
    dropped_records: int  # records lost because the backlog was full (or the process failed)
    backlog_bytes: int  # bytes the pipe has not taken yet
    backlog_high_water_bytes: int
    pipe_writes: int
    written_records: dict[str, int] | None  # per kind, from the writer process at close


def _package_root() -> str:
    return str(Path(dob_hil.__file__).resolve().parent.parent)


class LogWriter:
    """Writes the run's MCAP log through a separate writer process.

    ``metadata`` maps record name to key/value strings ("run", "versions", ...; "versions" and
    "log_format" are filled in if absent); ``attachments`` maps a file name ("design.json",
    "config.toml") to its bytes. A chunk is finished when it holds ``chunk_size_bytes`` or has
    been open ``chunk_interval_ns``; the batch goes to the process when :meth:`flush` finds it
    larger than ``flush_bytes`` or older than ``flush_interval_ns``, and always when it reaches
    ``batch_bytes``.
    """

    def __init__(
        self,
        path: Path,
        layout: LogLayout,
        *,
        metadata: Mapping[str, Mapping[str, str]] | None = None,
        attachments: Mapping[str, bytes] | None = None,
        chunk_size_bytes: int = DEFAULT_CHUNK_SIZE_BYTES,
        chunk_interval_ns: int = DEFAULT_CHUNK_INTERVAL_NS,
        compression: str = "zstd",
        max_backlog_bytes: int = DEFAULT_MAX_BACKLOG_BYTES,
        batch_bytes: int = DEFAULT_BATCH_BYTES,
        flush_bytes: int = DEFAULT_FLUSH_BYTES,
        flush_interval_ns: int = DEFAULT_FLUSH_INTERVAL_NS,
        startup_timeout_s: float = 20.0,
    ) -> None:
        self.path = Path(path)
        self.layout = layout
        if compression not in ("zstd", "lz4", "none"):
            raise LogWriteError(f"log compression: expected 'zstd', 'lz4' or 'none', got {compression!r}")
        if chunk_size_bytes < 1024:
            raise LogWriteError(f"log chunk_size_bytes: expected >= 1024, got {chunk_size_bytes}")
        self._check_path()
        self._sample_fields = sample_fields(layout)
        self._truth_fields = truth_fields(layout)
        self._pack_sample = record_struct(self._sample_fields).pack
        self._pack_can = record_struct(can_fields(CAN_DATA_BYTES)).pack
        self._pack_can_fd = record_struct(can_fields(CAN_FD_DATA_BYTES)).pack
        self._pack_truth = record_struct(self._truth_fields).pack
        self._sample_len = 4 + body_size(self._sample_fields)
        self._can_len = 4 + body_size(can_fields(CAN_DATA_BYTES))
        self._can_fd_len = 4 + body_size(can_fields(CAN_FD_DATA_BYTES))
        self._truth_len = 4 + body_size(self._truth_fields)

        self._batch = bytearray()
        self._batch_records = 0
        self._batch_bytes = batch_bytes
        self._flush_bytes = flush_bytes
        self._flush_interval_ns = flush_interval_ns
        self._last_push_ns = time.monotonic_ns()
        self._backlog: collections.deque[bytes | bytearray] = collections.deque()
        self._backlog_head = 0  # bytes of backlog[0] already written
        self._backlog_bytes = 0
        self._max_backlog = max_backlog_bytes
        self._high_water = 0
        self._enqueued_records = 0
        self._enqueued_bytes = 0
        self._dropped_records = 0
        self._pending_dropped = 0
        self._first_dropped_ns = 0
        self._pipe_writes = 0
        self._written_records: dict[str, int] | None = None
        self._failure: LogWriteError | None = None
        self._closed = False

        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (_package_root(), env.get("PYTHONPATH", "")) if p)
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "dob_hil.log.writer_process"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env=env,
            close_fds=True,
        )
        assert self._proc.stdin is not None and self._proc.stdout is not None
        self._fd = self._proc.stdin.fileno()
        self._status_fd = self._proc.stdout.fileno()
        self._status_buf = bytearray()
        with contextlib.suppress(OSError):  # a larger pipe absorbs the writer's chunk stalls
            fcntl.fcntl(self._fd, fcntl.F_SETPIPE_SZ, PIPE_CAPACITY_BYTES)
        try:
            self._start(metadata or {}, attachments or {}, chunk_size_bytes, chunk_interval_ns, compression)
            self._wait_status(pipe.STATUS_READY, startup_timeout_s)
        except BaseException:
            self._abort()
            raise
        os.set_blocking(self._fd, False)

    # ------------------------------------------------------------------ setup
    def _check_path(self) -> None:
        if self.path.is_dir():
            raise LogWriteError(f"log file {self.path}: is a directory")
        parent = self.path.parent
        if not parent.is_dir():
            raise LogWriteError(f"log file {self.path}: directory {parent} does not exist")
        if not os.access(parent, os.W_OK):
            raise LogWriteError(f"log file {self.path}: directory {parent} is not writable")

    def _start(
        self,
        metadata: Mapping[str, Mapping[str, str]],
        attachments: Mapping[str, bytes],
        chunk_size_bytes: int,
        chunk_interval_ns: int,
        compression: str,
    ) -> None:
        now_ns = time.time_ns()
        records = [
            pipe.control_record(
                pipe.OP_OPEN,
                {
                    "path": str(self.path.resolve()),
                    "layout": {
                        "n_states": self.layout.n_states,
                        "n_inputs": self.layout.n_inputs,
                        "n_outputs": self.layout.n_outputs,
                        "n_plant_states": self.layout.n_plant_states,
                    },
                    "chunk_size_bytes": chunk_size_bytes,
                    "chunk_interval_ns": chunk_interval_ns,
                    "compression": compression,
                    "library": f"dob_hil/{dob_hil.__version__}",
                },
            )
        ]
        for name, blob in attachments.items():
            media_type = _MEDIA_TYPES.get(Path(name).suffix, "application/octet-stream")
            fields = {"name": name, "media_type": media_type, "create_time": now_ns, "log_time": now_ns}
            records.append(pipe.control_record(pipe.OP_ATTACHMENT, fields, bytes(blob)))
        all_metadata: dict[str, Mapping[str, str]] = {"log_format": log_format_metadata(self.layout)}
        if "versions" not in metadata:
            all_metadata["versions"] = versions_metadata()
        all_metadata.update(metadata)
        for name, data in all_metadata.items():
            text = {str(k): v if isinstance(v, str) else json.dumps(v, default=str) for k, v in data.items()}
            records.append(pipe.control_record(pipe.OP_METADATA, {"name": name, "data": text}))
        records.append(pipe.control_record(pipe.OP_SYNC, {}))
        try:
            for record in records:
                self._write_blocking(record)
        except BrokenPipeError:
            pass  # the process died: _wait_status reports its message

    def _write_blocking(self, data: bytes | bytearray | memoryview) -> None:
        view = memoryview(data)
        while view:
            try:
                written = os.write(self._fd, view)
            except BlockingIOError:
                select.select([], [self._fd], [], 1.0)
                continue
            view = view[written:]

    def _read_status(self, timeout_s: float) -> list[dict[str, Any]]:
        """Status lines available within ``timeout_s`` (stops early at EOF); text lines kept as messages."""
        out: list[dict[str, Any]] = []
        deadline = time.monotonic() + timeout_s
        while True:
            while b"\n" in self._status_buf:
                line, _, rest = self._status_buf.partition(b"\n")
                self._status_buf = bytearray(rest)
                try:
                    obj = json.loads(line)
                    if not isinstance(obj, dict):
                        raise ValueError
                except ValueError:
                    obj = {"status": "text", "message": line.decode(errors="replace")}
                out.append(obj)
            if out:
                return out
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return out
            ready, _, _ = select.select([self._status_fd], [], [], remaining)
            if not ready:
                return out
            data = os.read(self._status_fd, 65536)
            if not data:
                if self._status_buf:
                    self._status_buf += b"\n"
                    continue
                out.append({"status": "eof"})
                return out
            self._status_buf += data

    def _wait_status(self, wanted: str, timeout_s: float) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        text: list[str] = []
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise LogWriteError(
                    f"log file {self.path}: the writer process did not answer {wanted!r} "
                    f"within {timeout_s:.1f} s"
                )
            for obj in self._read_status(remaining):
                status = obj.get("status")
                if status == wanted:
                    return obj
                if status == pipe.STATUS_ERROR:
                    raise LogWriteError(f"log file {self.path}: {obj.get('message')}")
                if status == "eof":
                    detail = "; ".join(text[-5:]) or f"exit status {self._proc.poll()}"
                    raise LogWriteError(
                        f"log file {self.path}: the writer process ended unexpectedly: {detail}"
                    )
                text.append(str(obj.get("message", obj)))

    def _close_pipe(self) -> None:
        stdin = self._proc.stdin
        if stdin is not None and not stdin.closed:
            with contextlib.suppress(OSError):
                os.set_blocking(self._fd, True)
                stdin.close()

    def _abort(self) -> None:
        self._close_pipe()
        try:
            self._proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        assert self._proc.stdout is not None
        self._proc.stdout.close()

    # ------------------------------------------------------------------ records (control thread)
    def sample(
        self,
        time_ns: int,
        rx_time_ns: int,
        tx_time_ns: int,
        lateness_ns: int,
        counts: Sequence[int],
        position: Sequence[float],
        x_ref: Sequence[float],
        x_hat: Sequence[float],
        x_bar: Sequence[float],
        u_fb: Sequence[float],
        u_dist: Sequence[float],
        u_cmd_A: Sequence[float],
        u_applied_A: Sequence[float],
        seq: int,
        compute_ns: int,
        dac_counts: Sequence[int],
        feedback_seq: int,
        flags: int,
    ) -> None:
        """One control period (``/dob_hil/sample``, log time ``time_ns``)."""
        try:
            self._batch += self._pack_sample(
                CH_SAMPLE, time_ns, self._sample_len, CDR_HEADER_U32,
                time_ns, rx_time_ns, tx_time_ns, lateness_ns,
                *counts, *position, *x_ref, *x_hat, *x_bar, *u_fb, *u_dist, *u_cmd_A, *u_applied_A,
                seq, compute_ns, *dac_counts, feedback_seq, flags,
            )  # fmt: skip
        except struct.error as exc:
            values = (
                time_ns, rx_time_ns, tx_time_ns, lateness_ns, counts, position, x_ref, x_hat, x_bar,
                u_fb, u_dist, u_cmd_A, u_applied_A, seq, compute_ns, dac_counts, feedback_seq, flags,
            )  # fmt: skip
            raise self._diagnose("sample", self._sample_fields, values, exc) from exc
        self._batch_records += 1
        if len(self._batch) >= self._batch_bytes:
            self._push()

    def frame(self, msg: can.Message, is_rx: bool) -> None:
        """One raw CAN frame, received or sent (``/dob_hil/can``, or ``/dob_hil/can_fd`` above 8 bytes).

        The log time is ``msg.timestamp`` (seconds, float) in integer ns; give the frames a
        timestamp on the loop's clock if they are to line up with the samples.
        """
        flags = (
            (CAN_FLAG_EXTENDED if msg.is_extended_id else 0)
            | (CAN_FLAG_ERROR if msg.is_error_frame else 0)
            | (CAN_FLAG_REMOTE if msg.is_remote_frame else 0)
            | (CAN_FLAG_FD if msg.is_fd else 0)
        )
        self.frame_raw(round(msg.timestamp * 1e9), msg.arbitration_id, is_rx, msg.dlc, msg.data or b"", flags)

    def frame_raw(
        self,
        timestamp_ns: int,
        arbitration_id: int,
        is_rx: bool,
        dlc: int,
        data: bytes | bytearray,
        flags: int,
    ) -> None:
        """One raw CAN frame from its parts (``flags`` as in CanFrame.flags)."""
        direction = CAN_RX if is_rx else CAN_TX
        try:
            if len(data) <= CAN_DATA_BYTES:
                record = self._pack_can(
                    CH_CAN, timestamp_ns, self._can_len, CDR_HEADER_U32,
                    timestamp_ns, arbitration_id, direction, dlc, flags, data,
                )  # fmt: skip
            else:
                if len(data) > CAN_FD_DATA_BYTES:
                    raise LogWriteError(f"CAN frame 0x{arbitration_id:x}: {len(data)} data bytes, at most 64")
                record = self._pack_can_fd(
                    CH_CAN_FD, timestamp_ns, self._can_fd_len, CDR_HEADER_U32,
                    timestamp_ns, arbitration_id, direction, dlc, flags, data,
                )  # fmt: skip
        except struct.error as exc:
            values = (timestamp_ns, arbitration_id, direction, dlc, flags, data)
            raise self._diagnose("frame", can_fields(CAN_FD_DATA_BYTES), values, exc) from exc
        self._batch += record
        self._batch_records += 1
        if len(self._batch) >= self._batch_bytes:
            self._push()

    def truth(
        self,
        time_ns: int,
        state: Sequence[float],
        disturbance_A: Sequence[float],
        applied_current_A: Sequence[float],
        period_index: int,
        drive_state: int,
    ) -> None:
        """The simulated drive's ground truth for one period (``/dob_hil/truth``)."""
        try:
            self._batch += self._pack_truth(
                CH_TRUTH, time_ns, self._truth_len, CDR_HEADER_U32,
                time_ns, *state, *disturbance_A, *applied_current_A, period_index, drive_state,
            )  # fmt: skip
        except struct.error as exc:
            values = (time_ns, state, disturbance_A, applied_current_A, period_index, drive_state)
            raise self._diagnose("truth", self._truth_fields, values, exc) from exc
        self._batch_records += 1
        if len(self._batch) >= self._batch_bytes:
            self._push()

    def event(
        self, time_ns: int, level: str, kind: str, message: str, data: Mapping[str, Any] | None = None
    ) -> None:
        """A state change, fault, overrun or warning (``/dob_hil/event``, JSON)."""
        if level not in EVENT_LEVELS:
            raise LogWriteError(f"event level: expected one of {', '.join(EVENT_LEVELS)}, got {level!r}")
        self._batch += self._event_record(time_ns, level, kind, message, data)
        self._batch_records += 1
        if len(self._batch) >= self._batch_bytes:
            self._push()

    @staticmethod
    def _event_record(
        time_ns: int, level: str, kind: str, message: str, data: Mapping[str, Any] | None
    ) -> bytes:
        obj = {
            "time_ns": int(time_ns),
            "level": level,
            "kind": kind,
            "message": message,
            "data": dict(data or {}),
        }
        payload = json.dumps(obj, default=str).encode()
        return PIPE_HEADER.pack(CH_EVENT, int(time_ns), len(payload)) + payload

    @staticmethod
    def _diagnose(
        what: str, fields: Sequence[Any], values: Sequence[Any], exc: struct.error
    ) -> LogWriteError:
        """Name the argument that did not pack (wrong length, type or range)."""
        for field, value in zip(fields, values, strict=False):
            fmt = "<" + (
                field.primitive.struct_char
                if field.count is None
                else f"{field.count}{field.primitive.struct_char}"
            )
            try:
                if field.count is None:
                    struct.pack(fmt, value)
                elif field.type == "uint8":
                    if len(value) > field.count:
                        raise struct.error(f"more than {field.count} bytes")
                else:
                    if len(value) != field.count:
                        return LogWriteError(
                            f"log {what}.{field.name}: expected {field.count} values, got {len(value)}"
                        )
                    struct.pack(fmt, *value)
            except (struct.error, TypeError) as field_exc:
                return LogWriteError(
                    f"log {what}.{field.name}: cannot pack {value!r} as {field.type}: {field_exc}"
                )
        return LogWriteError(f"log {what}: cannot pack the record: {exc}")

    # ------------------------------------------------------------------ hand-over
    def flush(self, force: bool = False) -> None:
        """Hand the batch to the writer process if it is due; never blocks.

        Due: ``force``, or the batch holds ``flush_bytes``, or ``flush_interval_ns`` passed since
        the last hand-over. Raises :class:`LogWriteError` once the writer process has failed.
        """
        if self._batch and (
            force
            or len(self._batch) >= self._flush_bytes
            or time.monotonic_ns() - self._last_push_ns >= self._flush_interval_ns
        ):
            self._push()
        elif self._backlog and force:
            self._drain()
        if self._failure is not None:
            raise self._failure

    def _push(self) -> None:
        """Move the batch to the backlog (or drop it, counted, if the backlog is full) and drain."""
        self._last_push_ns = time.monotonic_ns()
        batch, records = self._batch, self._batch_records
        self._batch = bytearray()
        self._batch_records = 0
        if self._failure is not None or self._closed:
            self._dropped_records += records
            return
        if self._backlog and self._backlog_bytes + len(batch) > self._max_backlog:
            self._drain()
        if self._backlog_bytes + len(batch) > self._max_backlog:
            if self._pending_dropped == 0:
                self._first_dropped_ns = PIPE_HEADER.unpack_from(batch, 0)[1]
            self._pending_dropped += records
            self._dropped_records += records
            return
        if self._pending_dropped:
            time_ns = PIPE_HEADER.unpack_from(batch, 0)[1]
            count = self._pending_dropped
            data = {"dropped_records": count, "first_dropped_time_ns": self._first_dropped_ns}
            text = f"log backlog full ({self._max_backlog} bytes): {count} records dropped"
            batch[0:0] = self._event_record(time_ns, "warning", "log_overflow", text, data)
            records += 1
            self._pending_dropped = 0
        self._enqueued_records += records
        self._enqueued_bytes += len(batch)
        self._backlog.append(batch)
        self._backlog_bytes += len(batch)
        self._high_water = max(self._high_water, self._backlog_bytes)
        self._drain()

    def _drain(self) -> None:
        """Write as much of the backlog as the pipe takes now."""
        backlog = self._backlog
        try:
            while backlog:
                head = backlog[0]
                view = memoryview(head)[self._backlog_head :] if self._backlog_head else head
                written = os.write(self._fd, view)
                self._pipe_writes += 1
                self._backlog_bytes -= written
                if written < len(view):
                    self._backlog_head += written
                    return
                backlog.popleft()
                self._backlog_head = 0
        except BlockingIOError:
            return
        except OSError as exc:  # EPIPE: the writer process has ended
            self._fail(f"the writer process stopped taking records ({exc})")

    def _fail(self, what: str) -> None:
        message = what
        for obj in self._read_status(2.0):
            if obj.get("status") in (pipe.STATUS_ERROR, "text"):
                message = str(obj.get("message"))
                break
        self._failure = LogWriteError(f"log file {self.path}: {message}")
        self._backlog.clear()  # enqueued, never written: written_records (None) tells
        self._backlog_bytes = 0

    # ------------------------------------------------------------------ close
    @property
    def stats(self) -> LogStats:
        return LogStats(
            enqueued_records=self._enqueued_records,
            enqueued_bytes=self._enqueued_bytes,
            dropped_records=self._dropped_records,
            backlog_bytes=self._backlog_bytes,
            backlog_high_water_bytes=self._high_water,
            pipe_writes=self._pipe_writes,
            written_records=self._written_records,
        )

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self, summary: Mapping[str, Any] | None = None, timeout_s: float = 60.0) -> None:
        """Flush everything, write the ``summary`` metadata record, finish the file, wait.

        Safe to call twice (the second call does nothing). Raises :class:`LogWriteError` if the
        writer process failed.
        """
        if self._closed:
            return
        try:
            if self._failure is None:
                self._push()
            self._closed = True
            if self._failure is None:
                full_summary: dict[str, Any] = dict(summary or {})
                full_summary.setdefault("exit_reason", "closed")
                full_summary.setdefault("dropped_records", self._dropped_records)
                full_summary.setdefault("log_backlog_high_water_bytes", self._high_water)
                if self._pending_dropped:
                    full_summary.setdefault("dropped_records_unreported", self._pending_dropped)
                os.set_blocking(self._fd, True)
                try:
                    while self._backlog:
                        head = self._backlog.popleft()
                        self._write_blocking(memoryview(head)[self._backlog_head :])
                        self._backlog_head = 0
                    self._backlog_bytes = 0
                    self._write_blocking(pipe.control_record(pipe.OP_CLOSE, {"summary": full_summary}))
                except OSError as exc:
                    self._fail(f"the writer process stopped taking records ({exc})")
                else:
                    self._close_pipe()
                    try:
                        answer = self._wait_status(pipe.STATUS_CLOSED, timeout_s)
                        self._written_records = {str(k): int(v) for k, v in answer.get("written", {}).items()}
                    except LogWriteError as exc:
                        self._failure = exc
        finally:
            self._closed = True
            self._abort()
        if self._failure is not None:
            raise self._failure

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc is None:
            self.close({"exit_reason": "closed"})
            return
        summary = {"exit_reason": f"exception: {type(exc).__name__}: {exc}"}
        try:
            self.close(summary)
        except LogWriteError as log_exc:
            exc.add_note(f"and closing the log failed: {log_exc}")
