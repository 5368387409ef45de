"""LogWriter: the control-thread side of the log.

The control thread only packs each record -- a complete MCAP Message record, with its per-channel
sequence number -- with one precomputed :class:`struct.Struct` and appends it to a local batch (a
``bytearray``). :meth:`LogWriter.flush` hands the batch to the writer process through a
non-blocking pipe; what the pipe does not take waits in a bounded backlog. When the backlog is
full the policy decides:

* ``backpressure=True`` (the default; lockstep, where nothing forces real time): the loop waits
  for the writer process, and the time it waited is counted (:attr:`LogStats.backpressure_wait_ns`,
  and ``log_backpressure_wait_ns`` in the summary). No record is ever dropped.
* ``backpressure=False`` (real time): whole batches are dropped, counted, and reported by a
  ``log_overflow`` event as soon as there is room again; the summary's ``dropped_records`` says
  how many, and :func:`dob_hil.log.check.check_sequences` finds the gaps.

Lockstep's per-period records from the bus and the simulated drive (each CAN frame, the ground
truth) are staged rather than packed where they happen: the frame hook of
:meth:`LogWriter.clocked_frame_hook` stages the frame with its time, and the sink of
:meth:`LogWriter.truth_hook` is a staging list's ``append`` (atomic under the GIL: any thread may
stage; the owner takes what was staged with :func:`_take`). The owner thread packs them into its
batch in one pass each time the batch grew by ``STAGE_BYTES`` (about 90 samples) and at every
hand-over, in their order per channel; packing a run of them costs about half what packing each one
in the middle of a period costs (BENCHMARKS.md, "Issue 16 lockstep, sixth pass"). The same records,
with the same sequence numbers and times, reach the file; only their interleaving across channels
within a batch differs.

Threads: the thread that made the writer owns it (the control thread). Records packed by any other
thread go to a lock-free queue (``collections.deque``), and staged frames and truth (the embedded
real-time drive's timer thread writes ground truth) to the staging lists; the owner moves both into
its batch at the next hand-over, so no batch is ever shared between threads. Each channel must be
written by one thread only (events: any).

A writer-process failure (a full disk, a file size limit) is raised as :class:`LogWriteError` on
the owner thread at the next hand-over, with how many records were lost.

``path`` equal to ``os.devnull`` runs without a writer process and without a file: the records are
packed (so a run costs what a logged run costs on the control thread) and discarded.
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import functools
import json
import os
import select
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Final, Protocol, TypeVar

import can

import dob_hil
from dob_hil.errors import LogWriteError
from dob_hil.log import pipe
from dob_hil.log.metadata import log_format_metadata, versions_metadata
from dob_hil.log.packers import compile_sample, compile_truth_records
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
    MESSAGE_HEADER,
    MESSAGE_LAYOUTS,
    OP_MESSAGE,
    TOPIC_CAN,
    TOPIC_CAN_FD,
    TOPIC_EVENT,
    TOPIC_SAMPLE,
    TOPIC_TRUTH,
    LogLayout,
    can_fields,
    encode_event_cdr,
    record_length,
    record_struct,
    sample_fields,
    truth_fields,
)

DEFAULT_CHUNK_SIZE_BYTES: Final = 256 * 1024
# the block layout's chunks (counted in per-record bytes, before they become blocks): a block is at
# most a chunk's run of records, and longer runs compress better (BENCHMARKS.md, "Log size")
DEFAULT_BLOCK_CHUNK_SIZE_BYTES: Final = 1024 * 1024
DEFAULT_CHUNK_INTERVAL_NS: Final = 25_000_000
DEFAULT_MAX_BACKLOG_BYTES: Final = 64 * 1024 * 1024
# The control thread hands batches over in flush() (after the command is sent): about one sample
# in 70 pays for the pipe write (10-15 us), so the p99 cost per sample stays that of packing.
# batch_bytes is only a safety valve for a caller that never flushes. The writer's lag is bounded
# by age: a batch is handed over once it is flush_interval_ns old, and the writer process finishes
# a chunk once it has been open chunk_interval_ns.
DEFAULT_BATCH_BYTES: Final = 256 * 1024
DEFAULT_FLUSH_BYTES: Final = 48 * 1024
DEFAULT_FLUSH_INTERVAL_NS: Final = 20_000_000
DEFAULT_STALL_TIMEOUT_S: Final = 60.0
# staged records (lockstep frames and truth) are packed each time the batch grew by this much
STAGE_BYTES: Final = 16 * 1024
_NEVER: Final = 1 << 62  # _next_bytes while staged records are packed (no re-entry)
PIPE_CAPACITY_BYTES: Final = 1 << 20
_MEDIA_TYPES: Final = {".json": "application/json", ".toml": "application/toml", ".txt": "text/plain"}


def attachment_media_type(name: str) -> str:
    """The media type a log gives an attachment called ``name`` (by its suffix)."""
    return _MEDIA_TYPES.get(Path(name).suffix, "application/octet-stream")


_U32: Final = 0xFFFFFFFF
# The writer process does no linear algebra: one BLAS thread. numpy's OpenBLAS otherwise starts a
# worker per CPU at import, and they spin for tens of milliseconds, taking a CPU from the control
# loop just as a run starts (on a 2-CPU machine 5-20 ms of a lockstep run's first 4,000 samples).
WRITER_THREAD_ENV: Final = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
assert (CAN_RX, CAN_TX) == (0, 1)  # _pack_staged_frames packs a frame's direction as ``not is_rx``
_LOG_TIME = struct.Struct("<Q")
_get_ident: Final = threading.get_ident
_T = TypeVar("_T")


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
    backpressure_wait_ns: int = 0  # time the owner thread waited for the writer (backpressure)


class TimeSource(Protocol):
    """Anything with the current time as an attribute (a simulated drive's core)."""

    @property
    def time_ns(self) -> int: ...


def _take(staged: list[_T]) -> list[_T]:
    """The items staged so far, removed from ``staged``: the owner thread takes a prefix while other
    threads may append (each slice operation is atomic under the GIL; what is appended in between
    stays staged)."""
    n = len(staged)
    taken = staged[:n]
    del staged[:n]
    return taken


def _index_of(items: list[Any], item: Any) -> int:
    """The position of ``item`` itself (not an equal one) in ``items``."""
    return next(i for i, x in enumerate(items) if x is item)


def message_flags(msg: can.Message) -> int:
    """A python-can message's kind as ``CanFrame.flags``: extended id, error, remote, FD."""
    return (
        (CAN_FLAG_EXTENDED if msg.is_extended_id else 0)
        | (CAN_FLAG_ERROR if msg.is_error_frame else 0)
        | (CAN_FLAG_REMOTE if msg.is_remote_frame else 0)
        | (CAN_FLAG_FD if msg.is_fd else 0)
    )


def _package_root() -> str:
    return str(Path(dob_hil.__file__).resolve().parent.parent)


class LogWriter:
    """Writes the run's MCAP log through a separate writer process.

    ``metadata`` maps record name to key/value strings ("run", "versions", ...; "versions" and
    "log_format" are filled in if absent); ``attachments`` maps a file name ("design.json",
    "config.toml") to its bytes. A chunk is finished when it holds ``chunk_size_bytes`` or has
    been open ``chunk_interval_ns`` (``chunk_size_bytes`` default: 256 KiB, 1 MiB for the block
    layout, ``message_layout="blocks"``: see :mod:`dob_hil.log.blocks`); the batch goes to the
    process when :meth:`flush` finds it larger than ``flush_bytes`` or older than
    ``flush_interval_ns``, and always when it reaches ``batch_bytes``. ``backpressure``: wait for
    the writer rather than drop (module docstring); a writer process that takes nothing for
    ``stall_timeout_s`` while the loop waits is a failure.
    """

    def __init__(
        self,
        path: Path,
        layout: LogLayout,
        *,
        metadata: Mapping[str, Mapping[str, str]] | None = None,
        attachments: Mapping[str, bytes] | None = None,
        chunk_size_bytes: int | None = None,
        chunk_interval_ns: int = DEFAULT_CHUNK_INTERVAL_NS,
        compression: str = "zstd",
        message_layout: str = "samples",
        max_backlog_bytes: int = DEFAULT_MAX_BACKLOG_BYTES,
        batch_bytes: int = DEFAULT_BATCH_BYTES,
        flush_bytes: int = DEFAULT_FLUSH_BYTES,
        flush_interval_ns: int = DEFAULT_FLUSH_INTERVAL_NS,
        backpressure: bool = True,
        stall_timeout_s: float = DEFAULT_STALL_TIMEOUT_S,
        startup_timeout_s: float = 20.0,
    ) -> None:
        self.path = Path(path)
        self.layout = layout
        if compression not in ("zstd", "lz4", "none"):
            raise LogWriteError(f"log compression: expected 'zstd', 'lz4' or 'none', got {compression!r}")
        if message_layout not in MESSAGE_LAYOUTS:
            raise LogWriteError(
                f"log layout: expected one of {', '.join(MESSAGE_LAYOUTS)}, got {message_layout!r}"
            )
        self.message_layout = message_layout
        if chunk_size_bytes is None:
            blocks = message_layout == "blocks"
            chunk_size_bytes = DEFAULT_BLOCK_CHUNK_SIZE_BYTES if blocks else DEFAULT_CHUNK_SIZE_BYTES
        if chunk_size_bytes < 1024:
            raise LogWriteError(f"log chunk_size_bytes: expected >= 1024, got {chunk_size_bytes}")
        self.null = str(self.path) == os.devnull
        if not self.null:
            self._check_path()
        self._sample_fields = sample_fields(layout)
        self._truth_fields = truth_fields(layout)
        self._pack_sample = record_struct(self._sample_fields).pack
        self._pack_can = record_struct(can_fields(CAN_DATA_BYTES)).pack
        self._pack_can_fd = record_struct(can_fields(CAN_FD_DATA_BYTES)).pack
        self._pack_truth = record_struct(self._truth_fields).pack
        self._sample_len = record_length(self._sample_fields)
        self._can_len = record_length(can_fields(CAN_DATA_BYTES))
        self._can_fd_len = record_length(can_fields(CAN_FD_DATA_BYTES))
        self._truth_len = record_length(self._truth_fields)
        if type(self).sample is LogWriter.sample:  # the same method, generated for the layout
            self.sample = compile_sample(  # type: ignore[method-assign]
                self,
                self._sample_fields,
                self._pack_sample,
                self._sample_len,
                functools.partial(LogWriter.sample, self),
            )
        # next MCAP sequence number per channel (each channel is written by one thread; events
        # from any thread take the lock)
        self._seq_sample = 0
        self._seq_can = 0
        self._seq_can_fd = 0
        self._seq_truth = 0
        self._seq_event = 0
        self._event_lock = threading.Lock()

        self._owner = threading.get_ident()
        self._foreign: collections.deque[bytes] = collections.deque()
        self._batch = bytearray()
        self._batch_records = 0
        self._batch_bytes = batch_bytes
        # the batch length at which an owner-thread append calls _batch_due
        self._next_bytes = min(STAGE_BYTES, batch_bytes)
        # staged records (lists: other threads only append, the owner takes a prefix, see _take)
        self._staged_frames: list[tuple[int, can.Message, bool]] = []
        self._staged_frame_ns = 0  # the last staged frame's log time
        self._staged_truth: list[tuple[Any, ...]] = []
        self._truth_records: Callable[[list[tuple[Any, ...]]], None] | None = None  # set by truth_hook
        self._flush_bytes = flush_bytes
        self._flush_interval_ns = flush_interval_ns
        self._last_push_ns = time.monotonic_ns()
        self._backlog: collections.deque[bytes | bytearray] = collections.deque()
        self._backlog_head = 0  # bytes of backlog[0] already written
        self._backlog_bytes = 0
        self._max_backlog = max_backlog_bytes
        self._backpressure = backpressure
        self._stall_timeout_ns = int(stall_timeout_s * 1e9)
        self._wait_ns = 0
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
        self._status_buf = bytearray()
        self._proc: subprocess.Popen[bytes] | None = None
        self._fd = -1
        self._status_fd = -1
        if self.null:
            return

        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (_package_root(), env.get("PYTHONPATH", "")) if p)
        env.update(WRITER_THREAD_ENV)
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
                    "message_layout": self.message_layout,
                    "library": f"dob_hil/{dob_hil.__version__}",
                },
            )
        ]
        for name, blob in attachments.items():
            fields = {
                "name": name,
                "media_type": attachment_media_type(name),
                "create_time": now_ns,
                "log_time": now_ns,
            }
            records.append(pipe.control_record(pipe.OP_ATTACHMENT, fields, bytes(blob)))
        all_metadata: dict[str, Mapping[str, str]] = {
            "log_format": log_format_metadata(self.layout, self.message_layout)
        }
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
                    if self._proc is not None and self._fd >= 0 and wanted != pipe.STATUS_READY:
                        self._fail("", obj)
                        assert self._failure is not None
                        raise self._failure
                    raise LogWriteError(f"log file {self.path}: {obj.get('message')}")
                if status == "eof":
                    detail = (
                        "; ".join(text[-5:]) or f"exit status {self._proc.poll() if self._proc else None}"
                    )
                    raise LogWriteError(
                        f"log file {self.path}: the writer process ended unexpectedly: {detail}"
                    )
                text.append(str(obj.get("message", obj)))

    def _close_pipe(self) -> None:
        if self._proc is None:
            return
        stdin = self._proc.stdin
        if stdin is not None and not stdin.closed:
            with contextlib.suppress(OSError):
                os.set_blocking(self._fd, True)
                stdin.close()

    def _abort(self) -> None:
        if self._proc is None:
            return
        self._close_pipe()
        try:
            self._proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        assert self._proc.stdout is not None
        self._proc.stdout.close()

    # ------------------------------------------------------------------ records (control thread)
    def _append(self, record: bytes) -> None:
        """Add one record to the owner's batch, or to the queue of records from other threads."""
        if threading.get_ident() != self._owner:
            self._foreign.append(record)
            return
        self._batch += record
        self._batch_records += 1
        if len(self._batch) >= self._next_bytes:
            self._batch_due()

    def _batch_due(self) -> None:
        """The batch reached ``_next_bytes``: pack the staged records into it, and hand it over
        once it holds ``batch_bytes``."""
        self._pack_staged()
        if len(self._batch) >= self._batch_bytes:
            self._push()

    def _pack_staged(self) -> None:
        """Pack the staged frames and truth into the owner's batch, each channel in its order."""
        self._next_bytes = _NEVER  # the packers append: no re-entry from here
        try:
            if self._staged_frames:
                self._pack_staged_frames()
            if self._staged_truth:
                records = self._truth_records
                assert records is not None  # only truth_hook's sink stages truth
                records(_take(self._staged_truth))
        finally:
            self._next_bytes = min(len(self._batch) + STAGE_BYTES, self._batch_bytes)

    def _restage_truth(self, rest: list[tuple[Any, ...]]) -> None:
        """Truth taken for packing but not packed (the records after one that raised): staged
        again, ahead of any staged since."""
        self._staged_truth[:0] = rest

    def _pack_staged_frames(self) -> None:
        """The staged ``(time_ns, msg, is_rx)`` frames as records (a classic frame's inline; any
        other, and one that does not pack, through :meth:`_frame_record`, which names it: the
        frames after one that raises stay staged)."""
        frames = _take(self._staged_frames)
        pack, can_len, batch = self._pack_can, self._can_len, self._batch
        n = n0 = self._seq_can
        fd0 = self._seq_can_fd
        last_ns = self._staged_frame_ns
        item = None
        try:
            for item in frames:
                t, msg, is_rx = item
                # non-decreasing, whatever the clock: a hook called from another thread (the
                # staging list takes any) may have read it before the frame ahead of it
                if t < last_ns:  # noqa: PLR1730 (a comparison, no call)
                    t = last_ns
                last_ns = t
                data = msg.data
                if not (msg.is_extended_id or msg.is_error_frame or msg.is_fd or len(data) > CAN_DATA_BYTES):
                    try:
                        batch += pack(
                            OP_MESSAGE, can_len, CH_CAN, n & _U32, t, t, CDR_HEADER_U32, t,
                            msg.arbitration_id, not is_rx, msg.dlc,  # not is_rx: CAN_TX (1) or CAN_RX (0)
                            CAN_FLAG_REMOTE if msg.is_remote_frame else 0, data,
                        )  # fmt: skip
                        n += 1
                        continue
                    except struct.error:
                        pass
                self._seq_can = n
                batch += self._frame_record(
                    t, msg.arbitration_id, is_rx, msg.dlc, data or b"", message_flags(msg)
                )
                n = self._seq_can
        except BaseException:
            # the frame that raised is dropped (named by the error), the ones after it stay staged
            done = 0 if item is None else _index_of(frames, item) + 1
            self._staged_frames[:0] = frames[done:]
            raise
        finally:
            self._seq_can = n
            self._staged_frame_ns = last_ns
            self._batch_records += n - n0 + self._seq_can_fd - fd0  # the records made, FD ones too

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
        n = self._seq_sample
        try:
            record = self._pack_sample(
                OP_MESSAGE, self._sample_len, CH_SAMPLE, n & _U32, time_ns, time_ns, CDR_HEADER_U32,
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
        self._seq_sample = n + 1
        if _get_ident() == self._owner:  # _append, inline (the per-period path)
            batch = self._batch
            batch += record
            self._batch_records += 1
            if len(batch) >= self._next_bytes:
                self._batch_due()
        else:
            self._foreign.append(record)

    def frame(self, msg: can.Message, is_rx: bool) -> None:
        """One raw CAN frame, received or sent (``/dob_hil/can``, or ``/dob_hil/can_fd`` above 8 bytes).

        The log time is ``msg.timestamp`` (seconds, float) in integer ns; give the frames a
        timestamp on the loop's clock if they are to line up with the samples.
        """
        self.frame_raw(
            round(msg.timestamp * 1e9),
            msg.arbitration_id,
            is_rx,
            msg.dlc,
            msg.data or b"",
            message_flags(msg),
        )

    def clocked_frame_hook(self, clock: TimeSource) -> Callable[[can.Message, bool], None]:
        """A link frame hook logging each frame at ``clock.time_ns`` when it passes (lockstep: the
        simulated drive's time, read as an attribute: a third of the hook's cost with a callable).

        The hook stages the frame with its time (module docstring): the owner thread packs it with
        the next run of staged records, as :meth:`frame_raw` would. The frame must not change once
        sent, as nothing in the project changes it. A subclass that overrides :meth:`frame_raw` gets
        a hook calling it at once."""
        if type(self).frame_raw is not LogWriter.frame_raw:
            frame_raw = self.frame_raw

            def general(msg: can.Message, is_rx: bool) -> None:
                frame_raw(
                    clock.time_ns, msg.arbitration_id, is_rx, msg.dlc, msg.data or b"", message_flags(msg)
                )

            return general
        stage = self._staged_frames.append

        def hook(msg: can.Message, is_rx: bool) -> None:
            stage((clock.time_ns, msg, is_rx))

        return hook

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
        self._append(self._frame_record(timestamp_ns, arbitration_id, is_rx, dlc, data, flags))

    def _frame_record(
        self,
        timestamp_ns: int,
        arbitration_id: int,
        is_rx: bool,
        dlc: int,
        data: bytes | bytearray,
        flags: int,
    ) -> bytes:
        """The record of :meth:`frame_raw` (its channel's sequence number taken)."""
        direction = CAN_RX if is_rx else CAN_TX
        try:
            if len(data) <= CAN_DATA_BYTES:
                n = self._seq_can
                record = self._pack_can(
                    OP_MESSAGE, self._can_len, CH_CAN, n & _U32, timestamp_ns, timestamp_ns,
                    CDR_HEADER_U32, timestamp_ns, arbitration_id, direction, dlc, flags, data,
                )  # fmt: skip
                self._seq_can = n + 1
            else:
                if len(data) > CAN_FD_DATA_BYTES:
                    raise LogWriteError(f"CAN frame 0x{arbitration_id:x}: {len(data)} data bytes, at most 64")
                n = self._seq_can_fd
                record = self._pack_can_fd(
                    OP_MESSAGE, self._can_fd_len, CH_CAN_FD, n & _U32, timestamp_ns, timestamp_ns,
                    CDR_HEADER_U32, timestamp_ns, arbitration_id, direction, dlc, flags, data,
                )  # fmt: skip
                self._seq_can_fd = n + 1
        except struct.error as exc:
            values = (timestamp_ns, arbitration_id, direction, dlc, flags, data)
            raise self._diagnose("frame", can_fields(CAN_FD_DATA_BYTES), values, exc) from exc
        return record

    def truth(
        self,
        time_ns: int,
        state: Sequence[float],
        disturbance_A: Sequence[float],
        applied_current_A: Sequence[float],
        period_index: int,
        drive_state: int,
    ) -> None:
        """The simulated drive's ground truth for one period (``/dob_hil/truth``); any one thread."""
        n = self._seq_truth
        try:
            record = self._pack_truth(
                OP_MESSAGE, self._truth_len, CH_TRUTH, n & _U32, time_ns, time_ns, CDR_HEADER_U32,
                time_ns, *state, *disturbance_A, *applied_current_A, period_index, drive_state,
            )  # fmt: skip
        except struct.error as exc:
            values = (time_ns, state, disturbance_A, applied_current_A, period_index, drive_state)
            raise self._diagnose("truth", self._truth_fields, values, exc) from exc
        self._seq_truth = n + 1
        self._append(record)

    def truth_hook(self) -> Callable[[tuple[Any, ...]], None]:
        """A ground-truth sink for a simulated drive: takes its truth tuple ``(period_index,
        time_ns, state, disturbance_A, applied_current_A, drive_state)`` (firmware_sim's
        ``GroundTruth``: one float each; a multi-axis drive's: a tuple per input) and logs it as
        :meth:`truth` does. The sink stages the tuple (a staging list's ``append``: any thread;
        module docstring); the owner thread packs a run of them in one generated loop
        (:func:`dob_hil.log.packers.compile_truth_records`), a multi-axis one and anything that does
        not pack through :meth:`truth` (which names what did not pack). A subclass that overrides
        :meth:`truth` gets a sink calling it at once."""
        truth = self.truth

        def general(t: tuple[Any, ...]) -> None:
            period_index, time_ns, state, disturbance_A, applied_A, drive_state = t
            if type(disturbance_A) is tuple:  # a multi-axis drive: one value per input already
                truth(time_ns, state, disturbance_A, applied_A, period_index, drive_state)
            else:
                truth(time_ns, state, (disturbance_A,), (applied_A,), period_index, drive_state)

        if type(self).truth is not LogWriter.truth:
            return general
        # generated for the plant's state count (dob_hil.log.packers): no starred argument
        self._truth_records = compile_truth_records(
            self, self.layout.n_plant_states, self._pack_truth, self._truth_len, general
        )
        return self._staged_truth.append

    def event(
        self, time_ns: int, level: str, kind: str, message: str, data: Mapping[str, Any] | None = None
    ) -> None:
        """A state change, fault, overrun or warning (``/dob_hil/event``); from any thread."""
        if level not in EVENT_LEVELS:
            raise LogWriteError(f"event level: expected one of {', '.join(EVENT_LEVELS)}, got {level!r}")
        self._append(self._event_record(time_ns, level, kind, message, data))

    def _event_record(
        self, time_ns: int, level: str, kind: str, message: str, data: Mapping[str, Any] | None
    ) -> bytes:
        payload = encode_event_cdr(
            int(time_ns), level, kind, message, json.dumps(dict(data or {}), default=str)
        )
        with self._event_lock:
            n = self._seq_event
            self._seq_event = n + 1
        head = MESSAGE_HEADER.pack(
            OP_MESSAGE, 22 + len(payload), CH_EVENT, n & _U32, int(time_ns), int(time_ns)
        )
        return head + payload

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
        """Hand the batch to the writer process if it is due (owner thread only).

        Due: ``force``, or the batch holds ``flush_bytes``, or ``flush_interval_ns`` passed since
        the last hand-over. Never blocks, except under backpressure with a full backlog. Raises
        :class:`LogWriteError` once the writer process has failed.
        """
        if (self._batch or self._foreign or self._staged_frames or self._staged_truth) and (
            force
            or len(self._batch) >= self._flush_bytes
            or time.monotonic_ns() - self._last_push_ns >= self._flush_interval_ns
        ):
            self._push()
        elif self._backlog and force:
            self._drain()
        if self._failure is not None:
            raise self._failure

    def _take_foreign(self) -> None:
        """Move the records other threads queued into the owner's batch."""
        foreign = self._foreign
        while foreign:
            self._batch += foreign.popleft()
            self._batch_records += 1

    def _push(self) -> None:
        """Move the batch to the backlog (waiting, or dropping counted, if the backlog is full) and drain."""
        self._last_push_ns = time.monotonic_ns()
        if self._staged_frames or self._staged_truth:
            self._pack_staged()
        if self._foreign:
            self._take_foreign()
        batch, records = self._batch, self._batch_records
        self._batch = bytearray()
        self._batch_records = 0
        self._next_bytes = min(STAGE_BYTES, self._batch_bytes)
        if not batch:
            return
        if self._failure is not None or self._closed:
            self._dropped_records += records
            return
        if self.null:
            self._enqueued_records += records
            self._enqueued_bytes += len(batch)
            return
        if self._poll_failed():
            self._dropped_records += records
            return
        if self._backlog and self._backlog_bytes + len(batch) > self._max_backlog:
            self._drain()
        # a batch larger than the whole backlog bound is taken when the backlog is empty
        if self._backlog_bytes and self._backlog_bytes + len(batch) > self._max_backlog:
            if self._backpressure:
                self._wait_for_room(len(batch))
                if self._poll_failed():
                    self._dropped_records += records
                    return
            else:
                if self._pending_dropped == 0:
                    self._first_dropped_ns = _LOG_TIME.unpack_from(batch, 15)[0]
                self._pending_dropped += records
                self._dropped_records += records
                return
        if self._pending_dropped:
            time_ns = _LOG_TIME.unpack_from(batch, 15)[0]
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

    def _wait_for_room(self, size: int) -> None:
        """Backpressure: block until the backlog takes ``size`` more bytes (time counted)."""
        t0 = last_progress = time.monotonic_ns()
        # a batch larger than the whole backlog bound goes once the backlog is empty
        while (
            self._backlog_bytes and self._backlog_bytes + size > self._max_backlog and self._failure is None
        ):
            select.select([self._status_fd], [self._fd], [], 1.0)
            before = self._backlog_bytes
            self._drain()
            self._poll_status()
            now = time.monotonic_ns()
            if self._backlog_bytes < before:
                last_progress = now
            elif now - last_progress > self._stall_timeout_ns:
                self._fail(f"the writer process took nothing for {self._stall_timeout_ns / 1e9:g} s")
        self._wait_ns += time.monotonic_ns() - t0

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

    def _poll_failed(self) -> bool:
        """Whether the writer process has failed (reading its reports without blocking)."""
        self._poll_status()
        return self._failure is not None

    def _poll_status(self) -> None:
        """Read what the writer process reported, without blocking; an error status fails the log."""
        if self._failure is not None or self._status_fd < 0:
            return
        ready, _, _ = select.select([self._status_fd], [], [], 0)
        if not ready:
            return
        for obj in self._read_status(0.5):
            if obj.get("status") in (pipe.STATUS_ERROR, "eof"):
                self._fail("", obj)
                return

    def _fail(self, what: str, report: dict[str, Any] | None = None) -> None:
        message = what
        if report is None or report.get("status") != pipe.STATUS_ERROR:
            for obj in self._read_status(2.0):
                if obj.get("status") in (pipe.STATUS_ERROR, "text"):
                    report = obj
                    break
        if report is not None and report.get("status") in (pipe.STATUS_ERROR, "text"):
            message = str(report.get("message"))
        if not message:
            message = "the writer process ended unexpectedly"
        written = report.get("written") if report is not None else None
        handed = (
            self._enqueued_records + self._batch_records + len(self._staged_frames) + len(self._staged_truth)
        )
        if isinstance(written, dict):
            in_file = sum(int(v) for k, v in written.items() if str(k).endswith("_written"))
            self._written_records = {str(k): int(v) for k, v in written.items()}
            lost = f"{handed - in_file} of {handed} records so far lost (the file holds {in_file})"
        else:
            lost = f"the records after the last finished chunk lost ({handed} handed over so far)"
        self._failure = LogWriteError(f"log file {self.path}: {message}; {lost}")
        self._backlog.clear()  # enqueued, never written
        self._backlog_bytes = 0

    # ------------------------------------------------------------------ close
    def _records_made(self) -> dict[str, int]:
        """Per topic, how many records were made (sequence numbers given out), dropped or not."""
        return {
            TOPIC_SAMPLE: self._seq_sample,
            TOPIC_CAN: self._seq_can,
            TOPIC_CAN_FD: self._seq_can_fd,
            TOPIC_TRUTH: self._seq_truth,
            TOPIC_EVENT: self._seq_event,
        }

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
            backpressure_wait_ns=self._wait_ns,
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
            if self.null:
                self._written_records = {}
            elif self._failure is None:
                full_summary: dict[str, Any] = dict(summary or {})
                full_summary.setdefault("exit_reason", "closed")
                full_summary.setdefault("dropped_records", self._dropped_records)
                full_summary.setdefault("log_backlog_high_water_bytes", self._high_water)
                full_summary.setdefault("log_backpressure_wait_ns", self._wait_ns)
                full_summary.setdefault("log_backpressure", self._backpressure)
                full_summary.setdefault("records_made", self._records_made())
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
