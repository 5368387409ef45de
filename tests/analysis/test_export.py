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
