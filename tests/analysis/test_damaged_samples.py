"""Sample records damaged inside intact chunks (duplicated, reordered, sequence numbers lost,
non-finite values): the streamed and the in-memory ``analyze`` give the same figures, say what is
wrong, and never call such a log complete."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_streamed import TINY_GROUP_BYTES, _in_memory, _same, rewrite_interleaved

import dob_hil.log.reader as reader_module
from dob_hil import cli
from dob_hil.analysis.streamed import analyze_streamed
from dob_hil.log import read_log

MID = 500


def _duplicated(s: np.ndarray) -> np.ndarray:
    return np.insert(s, MID, s[MID])


def _reordered(s: np.ndarray) -> np.ndarray:
    out = s.copy()
    out[[MID, MID + 1]] = s[[MID + 1, MID]]
    return out


def _sequence_repeated(s: np.ndarray) -> np.ndarray:
    out = s.copy()
    out["seq"][MID] = out["seq"][MID - 1]
    return out


def _sequence_gap(s: np.ndarray) -> np.ndarray:
    out = s.copy()
    out["seq"][MID:] += 100
    return out


DAMAGE = {
    "a sample written twice": (_duplicated, "out of sequence"),
    "two samples swapped": (_reordered, "out of sequence"),
    "a sequence number repeated": (_sequence_repeated, "out of sequence"),
    "100 sequence numbers lost": (_sequence_gap, None),
}


@pytest.mark.parametrize("case", list(DAMAGE))
def test_damaged_samples_are_reported_the_same_by_both_paths(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, case: str
) -> None:
    damage, says = DAMAGE[case]
    data = read_log(runs[("paper-sine", True)])
    path = rewrite_interleaved(data, tmp_path / "damaged.mcap", samples=damage(data.samples))
    if says is not None:  # a gap of 100 puts the truth 100 rows behind: more than MAX_PENDING tiny groups
        monkeypatch.setattr(reader_module, "GROUP_BYTES", TINY_GROUP_BYTES)
    expected = _in_memory(path, 0.0)
    _, got = analyze_streamed(path, 0.0)
    _same(expected, got)
    assert got["complete"] is False, got["warnings"]
    if says is not None:
        assert any(says in w for w in got["warnings"]), got["warnings"]
        assert got["out_of_sequence_samples"] >= 1
    else:
        assert got["dropped_samples"] == 100


def test_intact_log_has_no_sample_out_of_sequence(runs: dict[tuple[str, bool], Path]) -> None:
    got = _in_memory(runs[("paper-sine", True)], 0.0)
    assert got["complete"] is True and got["out_of_sequence_samples"] == 0
    _, streamed = analyze_streamed(runs[("paper-sine", True)], 0.0)
    assert streamed["complete"] is True and streamed["out_of_sequence_samples"] == 0


def test_non_finite_reference_gives_the_same_maximum_on_both_paths(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Non-finite values are left out of every tracking figure alike: the combined maximum too."""
    data = read_log(runs[("paper-sine", True)])
    samples = data.samples.copy()
    samples["x_ref"][MID : MID + 10] = np.inf
    path = rewrite_interleaved(data, tmp_path / "inf.mcap", samples=samples)
    monkeypatch.setattr(reader_module, "GROUP_BYTES", TINY_GROUP_BYTES)
    expected = _in_memory(path, 0.0)
    _, got = analyze_streamed(path, 0.0)
    _same(expected, got)
    assert got["tracking_error_max"] == max(got["tracking_error_max_per_output"])
    assert any("10 samples hold non-finite values" in w for w in got["warnings"]), got["warnings"]


def test_non_finite_values_are_one_clear_warning_on_the_command_line(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Not numpy's "invalid value encountered in matmul" (no file, no field): one line naming both."""
    data = read_log(runs[("paper-sine", True)])
    samples = data.samples.copy()
    samples["x_ref"][MID : MID + 10] = np.inf
    path = rewrite_interleaved(data, tmp_path / "inf.mcap", samples=samples)
    assert cli.main(["analyze", "--no-plots", str(path)]) == 0
    err = capsys.readouterr().err
    assert "encountered" not in err, err
    assert f"{path}: 10 samples hold non-finite values" in err, err


def _time_back(s: np.ndarray) -> np.ndarray:
    out = s.copy()
    out["time_ns"][MID] -= 10**12 if out["time_ns"][MID] > 10**12 else out["time_ns"][MID]
    return out


def _time_max(s: np.ndarray) -> np.ndarray:
    out = s.copy()
    out["time_ns"][MID] = np.iinfo(np.uint64).max
    return out


@pytest.mark.parametrize("damage", [_time_back, _time_max], ids=["time back to 0", "time 2**64 - 1"])
def test_sample_time_going_back_is_warned_and_both_paths_agree(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, damage: Any
) -> None:
    """One sample's time far off in the middle: the window still starts at the first sample at or
    after --from (not wherever a binary search on unsorted times lands), on both paths alike."""
    data = read_log(runs[("paper-sine", True)])
    path = rewrite_interleaved(data, tmp_path / "time.mcap", samples=damage(data.samples))
    monkeypatch.setattr(reader_module, "GROUP_BYTES", TINY_GROUP_BYTES)
    intact = _in_memory(runs[("paper-sine", True)], 0.1)
    expected = _in_memory(path, 0.1)
    _, got = analyze_streamed(path, 0.1)
    _same(expected, got)
    assert got["samples"] == intact["samples"]
    assert any("time goes back" in w for w in got["warnings"]), got["warnings"]


@pytest.mark.parametrize("how", [["--verify"], ["--design", "paper-sine"]], ids=["verify", "design"])
def test_replay_of_a_log_without_samples_is_one_line_with_status_2(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str], how: list[str]
) -> None:
    """Nothing to re-run is bad input, not a verdict ("DIFFERENT, 0 samples differ", exit 1)."""
    data = read_log(runs[("paper-sine", True)])
    path = rewrite_interleaved(data, tmp_path / "empty.mcap", samples=data.samples[:0], truth=data.truth[:0])
    rc = cli.main(["replay", str(path), *how])
    captured = capsys.readouterr()
    assert rc == 2, captured
    lines = [line for line in captured.err.splitlines() if ": error:" in line]
    assert len(lines) == 1 and "no samples" in lines[0], captured.err
    assert "Traceback" not in captured.err


def test_a_log_without_samples_says_so_on_both_paths(
    runs: dict[tuple[str, bool], Path], tmp_path: Path
) -> None:
    """Not "--from 0.1 s is past the log's end": the log has no samples at all."""
    data = read_log(runs[("paper-sine", True)])
    path = rewrite_interleaved(data, tmp_path / "empty.mcap", samples=data.samples[:0], truth=data.truth[:0])
    expected = _in_memory(path, 0.1)
    _, got = analyze_streamed(path, 0.1)
    _same(expected, got)
    assert got["samples"] == 0
    assert any("the log holds no samples" in w for w in got["warnings"]), got["warnings"]
    assert not any("past the log's end" in w for w in got["warnings"]), got["warnings"]
