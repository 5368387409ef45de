"""check_sequences on damaged numbering: the report is exact and costs memory for the numbers
present, not for the largest number (a flipped or crafted sequence number reaches 2**32)."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dob_hil.log.check import _summarise, check_sequences
from dob_hil.log.mcap_scan import scan
from dob_hil.log.schemas import MESSAGE_HEADER, OP_MESSAGE, TOPIC_SAMPLE


@pytest.mark.parametrize(
    ("numbers", "made", "missing", "first_missing", "duplicates", "last"),
    [
        ([0, 1, 2, 3], None, 0, [], 0, 3),
        ([0, 2, 5], None, 3, [1, 3, 4], 0, 5),
        ([3, 4], 8, 6, [0, 1, 2, 5, 6, 7], 0, 7),
        ([0, 0, 1], None, 0, [], 1, 1),
        ([0, 1, 2**32 - 1], None, 2**32 - 3, list(range(2, 12)), 0, 2**32 - 1),
        ([1, 5, 9, 20], 2**40, 2**40 - 4, [0, 2, 3, 4, 6, 7, 8, 10, 11, 12], 0, 2**40 - 1),
    ],
)
def test_gaps_are_counted_without_an_array_of_every_number(
    numbers: list[int], made: int | None, missing: int, first_missing: list[int], duplicates: int, last: int
) -> None:
    report = _summarise("t", [np.asarray(numbers)], made)
    assert (report.missing, report.first_missing, report.duplicates, report.last) == (
        missing,
        first_missing,
        duplicates,
        last,
    )


def test_a_flipped_sequence_number_is_reported_not_a_memory_error(tmp_path: Path, run_writer: Any) -> None:
    path = tmp_path / "flip.mcap"
    run_writer(path, 100, compression="none", chunk_interval_ns=10**12)
    blob = bytearray(path.read_bytes())
    at = 0
    while True:  # the sample numbered 50
        at = blob.find(bytes([OP_MESSAGE]), at + 1)
        _op, _length, channel, seq, _t, _p = MESSAGE_HEADER.unpack_from(blob, at)
        if channel == 1 and seq == 50:
            break
    struct.pack_into("<I", blob, at + 11, 0xFFFFFFF0)
    (chunk,) = scan(bytes(blob), str(path)).chunks  # uncompressed: fix its CRC so that it is read
    records = blob[chunk.data_offset : chunk.data_offset + chunk.data_length]
    struct.pack_into("<I", blob, chunk.offset + 9 + 24, zlib.crc32(records))  # after 3 x u64
    path.write_bytes(bytes(blob))
    report = check_sequences(path)[TOPIC_SAMPLE]
    assert report.messages == 100 and report.last == 0xFFFFFFF0
    assert report.missing == 0xFFFFFFF0 + 1 - 100  # 0..49, 51..99 and the flipped one are present
    assert report.first_missing == [50, *range(100, 109)]
