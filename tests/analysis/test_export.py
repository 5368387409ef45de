"""dob-hil export: frames through python-can's writers, read back with its readers; samples CSV."""

from __future__ import annotations

import csv
from pathlib import Path

import can
import numpy as np
import pytest

from dob_hil.analysis.export import scalar_columns
from dob_hil.analysis.frames import frame_messages
from dob_hil.cli import main
from dob_hil.log import read_log

READERS = {"blf": can.BLFReader, "asc": can.ASCReader, "csv": can.CSVReader}


@pytest.mark.parametrize("fmt", ["blf", "asc", "csv"])
def test_frames_read_back_equal_the_logged_frames(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, fmt: str, capsys: pytest.CaptureFixture[str]
) -> None:
    log_path = runs[("paper-sine", False)]
    out = tmp_path / f"frames.{fmt}"
    assert main(["export", str(log_path), "--format", fmt, "--out", str(out)]) == 0
    data = read_log(log_path)
    expected = list(frame_messages(data.frames, data.fd_frames))
    assert f"{len(expected)} frames" in capsys.readouterr().out
    with READERS[fmt](out) as reader:
        got = list(reader)
    assert len(got) == len(expected) == len(data.frames)
    t0_got, t0_exp = got[0].timestamp, expected[0].timestamp
    for g, e in zip(got, expected, strict=True):
        assert (g.arbitration_id, g.is_extended_id, g.dlc, bytes(g.data)) == (
            e.arbitration_id,
            e.is_extended_id,
            e.dlc,
            bytes(e.data),
        )
        assert g.is_remote_frame == e.is_remote_frame and g.is_error_frame == e.is_error_frame
        assert (g.timestamp - t0_got) == pytest.approx(e.timestamp - t0_exp, abs=2e-6)
        if fmt != "csv":  # python-can's CSV has no direction column
            assert g.is_rx == e.is_rx
    directions = {m.is_rx for m in expected}
    assert directions == {True, False}


def test_samples_csv_has_one_exact_column_per_scalar(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log_path = runs[("paper-step", True)]
    out = tmp_path / "samples.csv"
    assert main(["export", str(log_path), "--format", "csv", "--samples", "--out", str(out)]) == 0
    samples = read_log(log_path).samples
    with out.open(newline="") as f:
        rows = list(csv.reader(f))
    header, body = rows[0], rows[1:]
    columns = scalar_columns(samples)
    assert header == [name for name, _ in columns]
    assert "x_ref_1" in header and "u_cmd_a_0" in header
    assert len(body) == len(samples)
    for j, (_, values) in enumerate(columns):
        text = [row[j] for row in body]
        if values.dtype.kind == "f":
            parsed = np.array([float(t) for t in text])
            assert np.array_equal(parsed.view(np.uint64), np.ascontiguousarray(values).view(np.uint64))
        else:
            assert [int(t) for t in text] == values.tolist()


def test_default_output_beside_the_log_and_bad_combinations(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log_path = tmp_path / "copy.mcap"
    log_path.write_bytes(runs[("paper-step", False)].read_bytes())
    assert main(["export", str(log_path), "--format", "asc"]) == 0
    assert (tmp_path / "copy.asc").is_file()
    assert main(["export", str(log_path), "--format", "blf", "--samples"]) == 2
    assert main(["export", str(log_path), "--format", "csv", "--out", str(log_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "--samples" in err[0] and "--out" in err[1]


def _mixed_log(path: Path, layout: object, run: dict[str, str], back_in_time: bool = False) -> Path:
    """3,000 periods of a tx command, its udp_multicast echo, the feedback, and every 10th period a
    12-byte CAN FD frame, in chunks of 2 KiB (many groups); one tx frame stamped before the
    previous period's feedback if asked."""
    from dob_hil.log import LogWriter
    from dob_hil.log.schemas import CAN_FLAG_FD

    with LogWriter(path, layout, metadata={"run": run}, chunk_size_bytes=2048) as log:  # type: ignore[arg-type]
        for k in range(3000):
            t = 1_000_000_000 + k * 300_000
            stamp = t - 299_975 if back_in_time and k == 1500 else t + 10  # before the last feedback
            log.frame_raw(stamp, 0x201, False, 3, bytes([k & 0xFF, 1, 2]), 0)
            log.frame_raw(t + 20, 0x201, True, 3, bytes([k & 0xFF, 1, 2]), 0)  # our own echo
            log.frame_raw(t + 30, 0x181, True, 6, bytes([1, 2, 3, 4, 5, k & 0xFF]), 0)
            if k % 10 == 0:
                log.frame_raw(t + 15, 0x300, True, 12, bytes(range(12)), CAN_FLAG_FD)
            log.flush()
        log.flush(force=True)
    return path


def test_export_streams_groups_and_equals_python_cans_reader(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    """Streamed over many groups of chunks: every frame once, in time order across the classic and
    FD channels, without our echoes, as python-can's own reader of the log (the mcap library
    underneath, dob_hil's can.io plugin) yields them."""
    import dob_hil.log.reader as reader_module

    data = read_log(runs[("paper-sine", False)])
    path = _mixed_log(tmp_path / "mixed.mcap", data.layout, data.metadata["run"])
    monkeypatch.setattr(reader_module, "GROUP_BYTES", 4096)
    out = tmp_path / "mixed.blf"
    assert main(["export", str(path), "--format", "blf", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "6300 frames (blf), 3000 received copies of own frames left out" in captured.out
    assert captured.err == ""
    with can.LogReader(path) as reader:
        expected = list(reader)
    with can.BLFReader(out) as reader:
        got = list(reader)
    assert len(got) == len(expected) == 6300
    assert sum(m.is_fd for m in got) == 300
    for g, e in zip(got, expected, strict=True):
        assert (g.arbitration_id, g.is_fd, g.is_rx, g.dlc, bytes(g.data)) == (
            e.arbitration_id, e.is_fd, e.is_rx, e.dlc, bytes(e.data)
        )  # fmt: skip
        assert g.timestamp == pytest.approx(e.timestamp, abs=2e-6)


def test_a_frame_back_in_time_is_written_in_file_order_and_counted(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = read_log(runs[("paper-sine", False)])
    path = _mixed_log(tmp_path / "back.mcap", data.layout, data.metadata["run"], back_in_time=True)
    out = tmp_path / "back.asc"
    assert main(["export", str(path), "--format", "asc", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "6300 frames (asc)" in captured.out
    assert captured.err.strip().splitlines() == [
        f"dob-hil export: warning: {path}: 1 frames earlier than their channel's previous one, "
        "written in file order"
    ]
