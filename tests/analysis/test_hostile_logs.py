"""Hostile logs: crafted files must not make analyze/replay use gigabytes, print a traceback, or
sleep for years. Each file is crafted here."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
import zstandard
from analysis_support import rewrite_log
from mcap.data_stream import RecordBuilder
from mcap.records import Chunk, DataEnd, Header

from dob_hil.errors import LogReadError
from dob_hil.log import read_log
from dob_hil.log.mcap_scan import MAGIC

CLI = [sys.executable, "-m", "dob_hil.cli"]
MAX_RSS_MB = 400  # the crafted files claim gigabytes; a bounded reader stays far below


def _cli(*args: str) -> tuple[int, str, str, float]:
    """(exit status, stdout, stderr, peak RSS in MB) of one dob-hil command."""
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        proc = subprocess.Popen([*CLI, *args], stdout=out, stderr=err)
        # wait4 gives this child's own peak RSS (RUSAGE_CHILDREN: the largest of all children)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        return proc.returncode, out.read().decode(), err.read().decode(), usage.ru_maxrss / 1024


def _zstd_bomb(n_mib: int) -> bytes:
    """A zstd frame of ``n_mib`` MiB of zeros without a declared size: ~32 KB per GiB."""
    c = zstandard.ZstdCompressor(write_content_size=False).compressobj()
    return b"".join(c.compress(bytes(1 << 20)) for _ in range(n_mib)) + c.flush()


def _crafted(path: Path, chunks: list[tuple[bytes, int]]) -> Path:
    """An MCAP file of chunks (compressed data, declared uncompressed size) and nothing else."""
    builder = RecordBuilder()
    Header(profile="", library="crafted").write(builder)
    for data, size in chunks:
        Chunk(compression="zstd", data=data, message_start_time=0, message_end_time=0,
              uncompressed_crc=0, uncompressed_size=size).write(builder)  # fmt: skip
    DataEnd(0).write(builder)
    path.write_bytes(MAGIC + builder.end())
    return path


@pytest.fixture(scope="module")
def bomb() -> bytes:
    return _zstd_bomb(1024)  # 1 GiB of zeros in about 32 KB


def test_a_chunk_claiming_a_gigabyte_is_skipped_without_allocating_it(tmp_path: Path, bomb: bytes) -> None:
    path = _crafted(tmp_path / "bomb.mcap", [(bomb, 1 << 30)])
    assert path.stat().st_size < 40_000
    with pytest.raises(LogReadError, match="not a dob_hil log"):
        read_log(path)
    status, _, err, rss_mb = _cli("analyze", str(path), "--no-plots", "--json")
    assert status == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert rss_mb < MAX_RSS_MB


def test_many_chunks_each_claiming_what_the_ratio_allows_stay_bounded(tmp_path: Path, bomb: bytes) -> None:
    """Chunks that claim as much as their size allows (256x) but hold a bomb: each fails to
    decompress within its claim, and only a bounded number are in flight."""
    claim = 256 * len(bomb)
    path = _crafted(tmp_path / "bombs.mcap", [(bomb, claim)] * 40)
    status, _, err, rss_mb = _cli("analyze", str(path), "--no-plots", "--json")
    assert status == 2 and "Traceback" not in err
    assert rss_mb < MAX_RSS_MB


@pytest.fixture(scope="module")
def base_log(runs: dict[tuple[str, bool], Path]) -> Path:
    return runs[("paper-step", True)]


@pytest.mark.parametrize(
    ("name", "blob"),
    [
        ("design.json", b"[" * 200_000 + b"]" * 200_000),  # nested 200 000 deep
        ("design.json", b'{"name": "x", "period_ns": 1' + b"0" * 5000 + b"}"),  # an integer of 5001 digits
        ("design.json", b'{"Phi": [[1' + b"0" * 400 + b", 0]]}"),  # beyond float range
        ("config.toml", b"a = " + b"[" * 100_000 + b"]" * 100_000),
        ("config.toml", b"[drive]\ncurrent_limit_A = 1" + b"0" * 400 + b"\n"),
        ("config.toml", b"[drive]\ncurrent_limit_A = 1" + b"0" * 5000 + b"\n"),
    ],
)
def test_hostile_attachments_give_one_line_not_a_traceback(
    tmp_path: Path, base_log: Path, name: str, blob: bytes
) -> None:
    data = read_log(base_log)
    path = rewrite_log(data, tmp_path / "hostile.mcap", attachments={**data.attachments, name: blob})
    status, _, err, _ = _cli("analyze", str(path), "--no-plots")
    assert status == 0 and "Traceback" not in err, err
    warning = [line for line in err.splitlines() if name in line]
    assert len(warning) == 1 and len(warning[0]) < 400
    status, _, err, _ = _cli("replay", str(path), "--verify")
    assert "Traceback" not in err, err
    if name == "design.json":  # replay needs the design: one line, exit 2
        assert status == 2 and "design.json" in err.strip().splitlines()[-1]
    else:
        assert status in (0, 1)


def test_replay_to_bus_refuses_a_frame_far_in_the_future(tmp_path: Path, base_log: Path) -> None:
    data = read_log(base_log)
    frames = data.frames.copy()
    frames["timestamp_ns"][-1] = frames["timestamp_ns"][-2] + np.uint64(10**18)
    path = tmp_path / "future.mcap"
    from dob_hil.log import LogWriter

    with LogWriter(path, data.layout, metadata={"run": data.metadata["run"]}) as log:
        for ts, aid, direction, dlc, flags, payload in zip(
            *(frames[n].tolist() for n in frames.dtype.names or ()), strict=True
        ):
            log.frame_raw(ts, aid, direction == 0, dlc, bytes(payload[: min(dlc, 8)]), flags)
    status, _, err, _ = _cli("replay", str(path), "--to-bus", "-i", "virtual", "-c", f"hostile-{os.getpid()}")
    assert status == 2 and "Traceback" not in err
    errors = [line for line in err.strip().splitlines() if ": warning: " not in line]
    assert len(errors) == 1 and "refusing to replay" in errors[0]
