"""Every channel of a log, group of chunks by group of chunks, in bounded memory.

:func:`open_stream` maps the file (:mod:`dob_hil.log.mcap_scan`) and learns its channels;
:meth:`LogStream.blocks` then yields, for each group of chunks (~8 MiB decompressed, see
:data:`dob_hil.log.reader.GROUP_BYTES`), the messages of that group on every fixed-size channel
(as numpy structured arrays, restricted to the fields asked for) and its events. Only one group
and its blocks are held at a time, so a pass over an 8-hour log costs the memory of a few groups.
The reader's checks and warnings are those of :func:`dob_hil.log.reader.read_log` (they are
complete once :meth:`LogStream.blocks` is exhausted).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import mmap
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np

from dob_hil.log.reader import LogData, StructArray, _fixed_specs, _Reader, map_log
from dob_hil.log.schemas import TOPIC_CAN, TOPIC_CAN_FD, TOPIC_EVENT, TOPIC_SAMPLE, TOPIC_TRUTH, LogLayout


@dataclass(slots=True)
class Blocks:
    """The messages of one group of chunks, in file order, per channel."""

    samples: StructArray
    frames: StructArray
    fd_frames: StructArray
    truth: StructArray
    events: list[dict[str, Any]] = field(default_factory=list)


class LogStream:
    """An open log, read group by group (module docstring). Use as a context manager."""

    def __init__(
        self, path: Path, mm: mmap.mmap, fields: Mapping[str, Iterable[str] | None], events: bool
    ) -> None:
        self.path = path
        self._mm = mm
        keep = {topic: tuple(names) for topic, names in fields.items() if names is not None}
        topics = set(fields) | ({TOPIC_EVENT} if events else set())
        self._reader = _Reader(mm, str(path), topics, True, keep)
        self._reader._learn_channels()
        self.layout: LogLayout = self._reader._layout()
        self._fixed, self._event_channel = self._reader._outputs(self.layout, preallocate=False)
        self._empty: dict[str, StructArray] = {}
        for spec in _fixed_specs(self.layout):
            full = np.zeros(0, dtype=np.dtype(_spec_dtype(spec.fields)))
            names = keep.get(spec.topic)
            self._empty[spec.topic] = full if names is None else np.zeros(0, _subset(full.dtype, names))
        for out in self._fixed.values():
            self._empty[out.topic] = np.zeros(0, out.dtype)

    @property
    def counts(self) -> dict[str, int]:
        """Records per channel, from the message indexes (a block log's: its summary, or for a log
        cut short a pass over its blocks, made on the first call)."""
        return {out.topic: self._reader.counted(out) for out in self._fixed.values()}

    @property
    def warnings(self) -> list[str]:
        return self._reader.warnings

    def header(self) -> LogData:
        """The log without messages: metadata, attachments, layout, the warnings so far."""
        fmap = self._reader.fmap
        return LogData(
            samples=self._empty[TOPIC_SAMPLE],
            frames=self._empty[TOPIC_CAN],
            fd_frames=self._empty[TOPIC_CAN_FD],
            truth=self._empty[TOPIC_TRUTH],
            events=[],
            metadata=fmap.metadata,
            attachments=fmap.attachments,
            layout=self.layout,
            warnings=self.warnings,
            complete=fmap.complete and not self.warnings,
        )

    @property
    def complete(self) -> bool:
        """Closed cleanly and nothing lost (final once :meth:`blocks` is exhausted)."""
        return self._reader.fmap.complete and not self.warnings

    def blocks(self) -> Iterator[Blocks]:
        reader = self._reader
        by_topic = {out.topic: out for out in self._fixed.values()}
        for group in reader._groups():
            table = reader._table(group)
            got: dict[str, StructArray] = {}
            for topic, out in by_topic.items():
                out.out, out.filled = out.out[:0], 0  # a fresh array per group
                reader._gather_fixed(group, table, out)
                got[topic] = out.out[: out.filled]
            events: list[dict[str, Any]] = []
            if self._event_channel is not None:
                reader._gather_events(group, table, self._event_channel, events)
            reader._release(group)
            yield Blocks(
                samples=got.get(TOPIC_SAMPLE, self._empty[TOPIC_SAMPLE]),
                frames=got.get(TOPIC_CAN, self._empty[TOPIC_CAN]),
                fd_frames=got.get(TOPIC_CAN_FD, self._empty[TOPIC_CAN_FD]),
                truth=got.get(TOPIC_TRUTH, self._empty[TOPIC_TRUTH]),
                events=events,
            )

    def close(self) -> None:
        self._mm.close()

    def __enter__(self) -> LogStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _spec_dtype(fields: Any) -> np.dtype[np.void]:
    from dob_hil.log.schemas import msg_dtype

    return msg_dtype(fields)


def _subset(dtype: np.dtype[np.void], names: tuple[str, ...]) -> np.dtype[np.void]:
    assert dtype.fields is not None
    return np.dtype([(name, dtype.fields[name][0]) for name in names if name in dtype.fields])


M_MMAP_THRESHOLD: Final = -3  # glibc mallopt parameter
LARGE_BUFFER_BYTES: Final = 128 << 10


def return_large_buffers_to_the_os() -> bool:
    """Have glibc's malloc serve every allocation of 128 KiB or more with its own mmap, returned
    to the OS when freed (glibc's default raises that threshold as buffers are freed, after
    which the reader's chunk buffers, allocated by two threads, fragment the heap arenas and
    the resident size creeps up with the log's length). Process-wide; False where not glibc."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return bool(libc.mallopt(M_MMAP_THRESHOLD, LARGE_BUFFER_BYTES))
    except (OSError, AttributeError):
        return False


def open_stream(
    path: Path | str, fields: Mapping[str, Iterable[str] | None], *, events: bool = True
) -> LogStream:
    """Open ``path`` for a pass over the channels in ``fields`` (topic -> the fields to keep, None
    for all). Raises LogReadError for a file that is no log at all (as :func:`read_log`)."""
    p = Path(path)
    mm = map_log(p)
    try:
        return LogStream(p, mm, fields, events)
    except BaseException:
        mm.close()
        raise


__all__ = ["Blocks", "LogStream", "open_stream", "return_large_buffers_to_the_os"]
