"""Completeness of a log: every channel's MCAP sequence numbers, checked for gaps and duplicates.

The writer numbers each channel's messages 0, 1, 2, ... where the record is made (on the thread
that logs it, :mod:`dob_hil.log.pipe`), so in a complete log each channel holds every number
exactly once: a record that never reached the file (dropped under load in real time, lost in a
crash or to a failed disk) leaves a gap, and a record written twice (two threads handing over the
same batch) a duplicate. :func:`check_sequences` reads the numbers in bulk (from the message
indexes, like :func:`dob_hil.log.read_log`) and reports per topic; tests of the loop, the session
and the log call it on every log they make (:func:`assert_complete`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dob_hil.log.blocks import block_counts, expand_runs, gather
from dob_hil.log.reader import _Reader, map_log


@dataclass(frozen=True, slots=True)
class ChannelSequence:
    """One channel's sequence numbers: how many messages, which numbers are missing or repeated."""

    topic: str
    messages: int
    first: int | None
    last: int | None
    missing: int  # numbers below the count made (summary ``records_made``, else last + 1) absent
    duplicates: int  # messages whose number an earlier message already had
    first_missing: list[int] = field(default_factory=list)  # up to 10
    first_duplicates: list[int] = field(default_factory=list)  # up to 10

    @property
    def complete(self) -> bool:
        """Every number from 0 on, once. (``first`` is the first in file order: a record logged
        from another thread, such as a CiA 402 drive's SDO answer, may come after later ones.)"""
        return self.missing == 0 and self.duplicates == 0


def check_sequences(path: Path | str) -> dict[str, ChannelSequence]:
    """Per topic of the log at ``path``: its sequence numbers' gaps and duplicates (module docstring).

    Raises :class:`LogReadError` for a file that is no MCAP log. A damaged file is checked as far
    as it reads (what is lost shows as missing numbers).
    """
    path = Path(path)
    mm = map_log(path)
    try:
        reader = _Reader(mm, str(path), None, True)
        reader._learn_channels()
        topics = {c.id: c.topic for c in reader.fmap.channels.values()}
        parts: dict[int, list[np.ndarray]] = {cid: [] for cid in topics}
        made = _records_made(reader.fmap.metadata.get("summary", {}))
        blocks = reader.block_channels()
        for group in reader._groups():
            table = reader._table(group)
            seqs = gather(group.buf, np.dtype("<u4"), table.offsets + 11)
            for cid in np.unique(table.channels).tolist():
                mine = table.channels == cid
                if cid in blocks:  # a block numbers its first record: the others follow it
                    counts = block_counts(group.buf, table.offsets[mine], table.lengths[mine], blocks[cid])
                    counts[counts < 0] = 0  # a damaged block, which read_log skips: its records are lost
                    numbers = expand_runs(seqs[mine].astype(np.int64), counts, 1)
                    parts.setdefault(int(cid), []).append(numbers & 0xFFFFFFFF)
                else:
                    parts.setdefault(int(cid), []).append(seqs[mine])
            reader._release(group)
    finally:
        mm.close()
    out = {}
    for cid, chunks in sorted(parts.items()):
        topic = topics.get(cid, f"channel {cid}")
        out[topic] = _summarise(topic, chunks, made.get(topic))
    return out


def _records_made(summary: dict[str, str]) -> dict[str, int]:
    """The writer's count of records made per topic (its summary), {} if absent or unreadable."""
    try:
        made = json.loads(summary.get("records_made", "{}"))
    except (ValueError, RecursionError):
        return {}
    if not isinstance(made, dict):
        return {}
    return {str(k): v for k, v in made.items() if isinstance(v, int) and 0 <= v < 1 << 40}


def _summarise(topic: str, chunks: list[np.ndarray], made: int | None) -> ChannelSequence:
    seqs = np.concatenate(chunks).astype(np.int64) if chunks else np.zeros(0, dtype=np.int64)
    if len(seqs) == 0:
        return ChannelSequence(topic, 0, None, None, made or 0, 0, list(range(min(made or 0, 10))))
    unique, counts = np.unique(seqs, return_counts=True)
    repeated = unique[counts > 1]
    last = max(int(unique[-1]), (made or 0) - 1)
    # the gaps between the numbers present (no array as long as the numbers: a damaged or crafted
    # sequence number may be anywhere up to 2**32, the summary's count up to 2**40)
    gap_starts = np.concatenate(([0], unique + 1))
    gap_ends = np.concatenate((unique, [last + 1]))
    sizes = np.maximum(gap_ends - gap_starts, 0)
    first_missing: list[int] = []
    for start, size in zip(gap_starts[sizes > 0].tolist(), sizes[sizes > 0].tolist(), strict=True):
        first_missing += range(start, start + min(size, 10 - len(first_missing)))
        if len(first_missing) >= 10:
            break
    return ChannelSequence(
        topic=topic,
        messages=len(seqs),
        first=int(seqs[0]),
        last=last,
        missing=int(sizes.sum()),
        duplicates=int(np.sum(counts[counts > 1] - 1)),
        first_missing=first_missing,
        first_duplicates=repeated[:10].tolist(),
    )


def assert_complete(path: Path | str) -> dict[str, ChannelSequence]:
    """Raise AssertionError naming each channel with a missing or repeated sequence number."""
    report = check_sequences(path)
    bad = [
        f"{s.topic}: {s.messages} messages, {s.missing} missing (first {s.first_missing}), "
        f"{s.duplicates} duplicated (first {s.first_duplicates})"
        for s in report.values()
        if not s.complete
    ]
    assert not bad, f"{path}: " + "; ".join(bad)
    return report
