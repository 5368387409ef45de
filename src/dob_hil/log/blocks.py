"""The block layout: a chunk's per-record Message records rewritten as one message per run.

The control thread packs every record as its own MCAP Message record (:mod:`dob_hil.log.pipe`);
with ``[run] log_layout = "blocks"`` the writer process rewrites each chunk before compressing it
(:func:`to_blocks`): the records of each fixed-size channel become block messages, each a run of
consecutive records (sequence numbers one apart, log times non-decreasing) as a ros2msg sequence
(:func:`dob_hil.log.schemas.block_msg_text`). Events stay one message each. A block's sequence
number and log time are its first record's and its publish time its last record's, so a gap in a
channel's records still shows as a gap between its blocks (:mod:`dob_hil.log.check`). The chunk
declares its end as its last record's time (``ChunkedFile.finish_chunk``: the greatest publish
time), so a read by time finds every record of it; MCAP's own readers only see a wider range.

Why: a Message record costs 31 bytes of header and 16 bytes of (uncompressed) message index, so at
four records per sample they were 64 of the 223 bytes a lockstep sample took; a block pays them
once per run (BENCHMARKS.md, "Log size").
"""

from __future__ import annotations

import itertools
import struct
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from dob_hil.log.schemas import (
    BLOCK_HEAD_BYTES,
    CDR_HEADER,
    CDR_HEADER_U32,
    MESSAGE_RECORD_OVERHEAD,
    OP_MESSAGE,
)

_U32_MASK: Final = 0xFFFFFFFF
_BLOCK_HEAD = struct.Struct("<BQHIQQ4sII")  # Message header, CDR header, count, padding
_RECORD_BODY: Final = MESSAGE_RECORD_OVERHEAD + 4  # a record's body starts after its CDR header


def gather(
    buf: bytes | npt.NDArray[np.uint8], dtype: np.dtype[Any], offsets: npt.NDArray[np.int64]
) -> npt.NDArray[Any]:
    """Items of ``dtype`` starting at arbitrary byte ``offsets`` of ``buf`` (a one-byte-stride view)."""
    count = len(buf) - dtype.itemsize + 1
    if count <= 0:
        return np.zeros(len(offsets), dtype=dtype)
    if dtype.names is not None:  # structured: gather raw bytes, then view (much faster)
        void = np.dtype((np.void, dtype.itemsize))
        return np.ndarray((count,), void, buf, 0, (1,))[offsets].view(dtype)
    return np.ndarray((count,), dtype, buf, 0, (1,))[offsets]


def gather_ints(
    buf: bytes | npt.NDArray[np.uint8], dtype: str, offsets: npt.NDArray[np.int64]
) -> npt.NDArray[np.int64]:
    """Integers of ``dtype`` at byte ``offsets`` of ``buf`` (:func:`gather`), as int64."""
    return gather(buf, np.dtype(dtype), offsets).astype(np.int64)


def expand_runs(
    firsts: npt.NDArray[np.int64], counts: npt.NDArray[np.int64], step: int
) -> npt.NDArray[np.int64]:
    """``firsts[i] + j * step`` for ``j < counts[i]``, run after run (a block's records from its first)."""
    before = np.cumsum(counts) - counts  # records in the runs before each
    index_in_run = np.arange(int(counts.sum()), dtype=np.int64) - np.repeat(before, counts)
    return np.repeat(firsts, counts) + index_in_run * step


# a block's Message record length field: this, plus its records' bytes
BLOCK_LENGTH_BASE: Final = MESSAGE_RECORD_OVERHEAD - 9 + 4 + BLOCK_HEAD_BYTES


def block_record_length(count: int, stride: int) -> int:
    """The Message record length field of a block of ``count`` records of ``stride`` bytes."""
    return BLOCK_LENGTH_BASE + count * stride


def block_counts(
    buf: bytes, offsets: npt.NDArray[np.int64], lengths: npt.NDArray[np.int64], stride: int
) -> npt.NDArray[np.int64]:
    """The record count of each block message (Message records at ``offsets`` of ``buf``, with
    their length fields ``lengths``, each lying within ``buf``), -1 for one that is damaged: too
    short, not CDR, or a length that does not fit its count. The one rule every reader applies."""
    long_enough = lengths >= BLOCK_LENGTH_BASE
    head = np.where(long_enough, offsets + MESSAGE_RECORD_OVERHEAD, 0)  # the CDR header
    cdr = gather_ints(buf, "<u4", head)
    counts = gather_ints(buf, "<u4", np.where(long_enough, head + 4, 0))
    good = long_enough & (cdr == CDR_HEADER_U32) & (lengths == BLOCK_LENGTH_BASE + counts * stride)
    return np.where(good, counts, -1)


def payload_block_count(payload: bytes, stride: int) -> int:
    """:func:`block_counts`' rule on one block message's payload (as an MCAP reader gives it,
    from its CDR header on): its record count, or -1 for a damaged block."""
    if len(payload) < 4 + BLOCK_HEAD_BYTES or payload[:4] != CDR_HEADER:
        return -1
    (count,) = struct.unpack_from("<I", payload, 4)
    return count if len(payload) == 4 + BLOCK_HEAD_BYTES + count * stride else -1


def first_record_offsets(offsets: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """Where the first record of each block message (Message records at ``offsets``) starts."""
    return offsets + MESSAGE_RECORD_OVERHEAD + 4 + BLOCK_HEAD_BYTES


def to_blocks(
    data: bytes, offsets: npt.NDArray[np.int64], bodies: dict[int, tuple[int, int]]
) -> tuple[bytes, list[int], dict[int, int]]:
    """Rewrite the Message records of a chunk (``data``, records at ``offsets``) as blocks.

    ``bodies`` maps each block channel id to (record body size, stride). Returns the new chunk
    data, its record offsets, and the records per block channel. Records of other channels are
    kept as they are; every record lands in the output (none is dropped), each block where its
    first record was. A record of a block channel whose length is not that channel's raises
    ValueError (the writer made it: a defect, not damage).
    """
    buf = np.frombuffer(data, dtype=np.uint8)
    channels = gather_ints(buf, "<u2", offsets + 9)
    lengths = gather_ints(buf, "<u8", offsets + 1)
    pieces: list[tuple[int, bytes]] = []  # (position of the first record, record bytes)
    counts: dict[int, int] = {}
    in_block = np.zeros(len(offsets), dtype=bool)
    for channel_id, (body, stride) in bodies.items():
        where = np.flatnonzero(channels == channel_id)
        if len(where) == 0:
            continue
        expected = MESSAGE_RECORD_OVERHEAD - 9 + 4 + body
        if np.any(lengths[where] != expected):
            raise ValueError(f"channel {channel_id}: a record of another length than {expected}")
        in_block[where] = True
        starts = offsets[where]
        seqs = gather_ints(buf, "<u4", starts + 11)
        times = gather_ints(buf, "<u8", starts + 15)
        breaks = np.flatnonzero((seqs[1:] != ((seqs[:-1] + 1) & _U32_MASK)) | (times[1:] < times[:-1])) + 1
        rows = np.zeros((len(where), stride), dtype=np.uint8)
        rows[:, :body] = buf[(starts + _RECORD_BODY)[:, None] + np.arange(body)]
        bounds = [0, *breaks.tolist(), len(where)]
        for a, b in itertools.pairwise(bounds):
            n = b - a
            head = _BLOCK_HEAD.pack(
                OP_MESSAGE, block_record_length(n, stride), channel_id, int(seqs[a]),
                int(times[a]), int(times[b - 1]), CDR_HEADER, n, 0,
            )  # fmt: skip
            pieces.append((int(where[a]), head + rows[a:b].tobytes()))
        counts[channel_id] = len(where)
    for i in np.flatnonzero(~in_block).tolist():
        start = int(offsets[i])
        pieces.append((i, data[start : start + 9 + int(lengths[i])]))
    pieces.sort(key=lambda p: p[0])
    out_offsets: list[int] = []
    pos = 0
    for _, piece in pieces:
        out_offsets.append(pos)
        pos += len(piece)
    return b"".join(p for _, p in pieces), out_offsets, counts


__all__ = [
    "BLOCK_LENGTH_BASE",
    "block_counts",
    "block_record_length",
    "expand_runs",
    "first_record_offsets",
    "gather",
    "gather_ints",
    "payload_block_count",
    "to_blocks",
]
