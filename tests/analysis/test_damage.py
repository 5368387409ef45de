"""Truncated and corrupted logs: a clear one-line error (exit 2) or the readable prefix with
warnings on stderr naming what was lost; never a traceback."""

from __future__ import annotations

import json
import random
from pathlib import Path

import pytest

from dob_hil.cli import main
from dob_hil.log.mcap_scan import scan
from dob_hil.log.schemas import TOPIC_SAMPLE

N_CUTS = 100
N_FLIPS = 40


def _check(rc: int, out: str, err: str, command: str) -> None:
    assert "Traceback" not in err and "Traceback" not in out
    if rc == 2:
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"dob-hil {command}: error:"), err
        return
    assert rc in (0, 1), (rc, err)


def test_analyze_a_log_cut_at_100_random_points(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blob = runs[("paper-sine", True)].read_bytes()
    rng = random.Random(20001)
    cut_path = tmp_path / "cut.mcap"
    outcomes = {0: 0, 2: 0}
    for size in sorted(rng.sample(range(len(blob)), N_CUTS)):
        cut_path.write_bytes(blob[:size])
        rc = main(["analyze", str(cut_path), "--json", "--no-plots", "--from", "0"])
        captured = capsys.readouterr()
        _check(rc, captured.out, captured.err, "analyze")
        outcomes[rc] += 1
        if rc == 0:
            (metrics,) = json.loads(captured.out)  # stdout holds the JSON and nothing else
            assert "warning" in captured.err and metrics["complete"] is False
            assert metrics["warnings"]
    assert outcomes[0] > N_CUTS // 2  # most cuts leave a readable prefix


def test_analyze_a_log_with_flipped_bytes(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blob = runs[("paper-step", True)].read_bytes()
    rng = random.Random(777)
    path = tmp_path / "flipped.mcap"
    for i in range(N_FLIPS):
        damaged = bytearray(blob)
        for _ in range(1 + i % 4):  # one to four flipped bytes
            pos = rng.randrange(len(damaged))
            damaged[pos] ^= 1 << rng.randrange(8)
        path.write_bytes(bytes(damaged))
        rc = main(["analyze", str(path), "--json", "--no-plots"])
        captured = capsys.readouterr()
        _check(rc, captured.out, captured.err, "analyze")
        if rc == 0:
            json.loads(captured.out)


def test_replay_and_export_of_damaged_logs(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blob = runs[("paper-step", False)].read_bytes()
    rng = random.Random(99)
    path = tmp_path / "damaged.mcap"
    for size in sorted(rng.sample(range(len(blob)), 12)):
        path.write_bytes(blob[:size])
        for argv, command in (
            (["replay", str(path), "--verify"], "replay"),
            (["export", str(path), "--format", "asc", "--out", str(tmp_path / "x.asc")], "export"),
        ):
            rc = main(argv)
            captured = capsys.readouterr()
            _check(rc, captured.out, captured.err, command)


@pytest.mark.parametrize("content", [b"", b"not an mcap file at all\n" * 10])
def test_not_a_log(tmp_path: Path, content: bytes, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "bad.mcap"
    path.write_bytes(content)
    assert main(["analyze", str(path)]) == 2
    _check(2, "", capsys.readouterr().err, "analyze")
    assert main(["analyze", str(tmp_path / "missing.mcap")]) == 2
    _check(2, "", capsys.readouterr().err, "analyze")


def test_a_log_cut_before_its_first_sample_chunk_is_one_line(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Cut inside the first chunk that holds samples: no samples are left, and replay's one line
    says why (the truncation) instead of warnings followed by an error. The writer closes chunks
    by size or age, so where that chunk lies is read from the file, not assumed."""
    blob = runs[("paper-step", False)].read_bytes()
    fmap = scan(blob)
    sample_id = next(c.id for c in fmap.channels.values() if c.topic == TOPIC_SAMPLE)
    first = next(c for c in fmap.chunks if sample_id in c.indexes)
    path = tmp_path / "cut.mcap"
    one_line_refusals = 0
    for size in sorted({first.offset + 1, (first.offset + first.end) // 2, first.end - 1, first.end + 1}):
        path.write_bytes(blob[:size])
        for argv, command in (
            (["replay", str(path), "--verify"], "replay"),
            (["replay", str(path), "--design", "paper-step"], "replay"),
        ):
            rc = main(argv)
            captured = capsys.readouterr()
            _check(rc, captured.out, captured.err, command)
            if rc == 2 and "no samples (" in captured.err and "truncated" in captured.err:
                one_line_refusals += 1
    assert one_line_refusals == 6  # every cut inside the chunk, by both commands
