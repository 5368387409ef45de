"""Truncated and corrupted logs: the readable part and a warning, or LogReadError; never a traceback."""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dob_hil.errors import LogReadError
from dob_hil.log import LogData, read_log
from dob_hil.log.mcap_scan import MAGIC, scan


@pytest.fixture(scope="module")
def full(small_log: tuple[Path, Any, Any]) -> tuple[bytes, LogData]:
    path = small_log[0]
    data = read_log(path)
    assert data.complete and data.warnings == []
    return path.read_bytes(), data


def _read_bytes(tmp_path: Path, blob: bytes, name: str = "damaged.mcap") -> LogData:
    path = tmp_path / name
    path.write_bytes(blob)
    return read_log(path)


def _assert_rows_from(part: np.ndarray, whole: np.ndarray, key: str) -> None:
    """Every row of ``part`` is the row of ``whole`` with the same key, byte for byte, in order."""
    keys = part[key].astype(np.int64)
    assert (np.diff(keys) > 0).all()
    index = {int(v): i for i, v in enumerate(whole[key])}
    rows = np.array([index[int(v)] for v in keys], dtype=np.int64)
    assert part.tobytes() == whole[rows].tobytes()


@pytest.mark.parametrize(
    ("blob", "match"),
    [
        (b"", "empty file"),
        (b"hello world, not a log at all", "not an MCAP file"),
        (MAGIC + b"\x01\x10", "ends inside its header"),
        (MAGIC + b"\x06" + (5).to_bytes(8, "little") + bytes(5), "unreadable MCAP header"),
    ],
)
def test_not_a_log_raises_log_read_error(tmp_path: Path, blob: bytes, match: str) -> None:
    with pytest.raises(LogReadError, match=match):
        _read_bytes(tmp_path, blob)


def test_missing_file_raises_log_read_error(tmp_path: Path) -> None:
    with pytest.raises(LogReadError, match="cannot read"):
        read_log(tmp_path / "missing.mcap")


def test_cut_at_100_points_gives_the_prefix(tmp_path: Path, full: tuple[bytes, LogData]) -> None:
    blob, whole = full
    rnd = random.Random(4)
    cuts = sorted(rnd.randrange(1, len(blob)) for _ in range(100))
    recovered = []
    for cut in cuts:
        try:
            data = _read_bytes(tmp_path, blob[:cut])
        except LogReadError:
            continue
        assert data.warnings, f"cut at {cut}: no warning"
        assert not data.complete
        n = len(data.samples)
        assert data.samples.tobytes() == whole.samples[:n].tobytes()
        assert data.frames.tobytes() == whole.frames[: len(data.frames)].tobytes()
        assert data.truth.tobytes() == whole.truth[: len(data.truth)].tobytes()
        assert data.events == whole.events[: len(data.events)]
        recovered.append(n)
    assert recovered == sorted(recovered)  # a longer prefix never recovers less
    assert recovered[-1] > 1500  # cuts in the summary lose nothing or little


def test_truncation_warning_names_the_lost_chunk(tmp_path: Path, full: tuple[bytes, LogData]) -> None:
    blob, _ = full
    chunk = scan(blob).chunks[10]
    data = _read_bytes(tmp_path, blob[: chunk.offset + 100])
    expected = (
        f"log truncated at byte {chunk.offset + 100}: "
        f"the last chunk (starting at byte {chunk.offset}) is incomplete; 1 chunk lost"
    )
    assert expected in data.warnings, data.warnings


def test_flip_bytes_at_100_points(tmp_path: Path, full: tuple[bytes, LogData]) -> None:
    blob, whole = full
    rnd = random.Random(7)
    silent = 0
    for _ in range(100):
        pos = rnd.randrange(len(blob))
        damaged = bytearray(blob)
        damaged[pos] ^= 1 << rnd.randrange(8)
        try:
            data = _read_bytes(tmp_path, bytes(damaged))
        except LogReadError:
            continue
        _assert_rows_from(data.samples, whole.samples, "seq")
        _assert_rows_from(data.truth, whole.truth, "period_index")
        _assert_rows_from(data.frames, whole.frames, "timestamp_ns")
        if not data.warnings:  # undetectable damage (text of a metadata record): no data lost
            silent += 1
            assert data.samples.tobytes() == whole.samples.tobytes()
            assert data.frames.tobytes() == whole.frames.tobytes()
            assert data.truth.tobytes() == whole.truth.tobytes()
            assert data.events == whole.events
    assert silent < 30


def test_bad_chunk_in_the_middle_is_skipped_with_a_warning(
    tmp_path: Path, full: tuple[bytes, LogData]
) -> None:
    blob, whole = full
    chunk = scan(blob).chunks[20]
    damaged = bytearray(blob)
    damaged[chunk.data_offset + chunk.data_length // 2] ^= 0xFF
    data = _read_bytes(tmp_path, bytes(damaged))
    assert any(f"chunk at byte {chunk.offset}" in w for w in data.warnings), data.warnings
    lost = len(whole.samples) - len(data.samples)
    assert 0 < lost < 40  # one 4 KiB chunk holds ~10-20 periods
    _assert_rows_from(data.samples, whole.samples, "seq")
    assert data.samples["seq"][-1] == whole.samples["seq"][-1]  # later chunks still read


def test_corrupt_message_index_is_rebuilt_from_the_chunk(tmp_path: Path, full: tuple[bytes, LogData]) -> None:
    blob, whole = full
    chunk = scan(blob).chunks[5]
    pairs_offset, _count = chunk.indexes[1]  # the sample channel's (log_time, offset) pairs
    damaged = bytearray(blob)
    damaged[pairs_offset + 8] ^= 0x04  # first entry's offset now points into the wrong place
    data = _read_bytes(tmp_path, bytes(damaged))
    assert data.warnings == [
        f"chunk at byte {chunk.offset}: its message index is damaged; re-indexed from its records"
    ]
    assert data.samples.tobytes() == whole.samples.tobytes()


def test_log_killed_before_the_first_chunk(tmp_path: Path, full: tuple[bytes, LogData]) -> None:
    blob, _ = full
    first = scan(blob).chunks[0]
    data = _read_bytes(tmp_path, blob[: first.offset])
    assert len(data.samples) == 0 and data.samples.dtype.names is not None
    assert data.layout.n_states == 2  # from the log_format metadata
    assert data.warnings
