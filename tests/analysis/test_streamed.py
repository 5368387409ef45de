"""`analyze` streamed over groups of chunks: the figures of the in-memory path, in bounded memory."""

from __future__ import annotations

import json
import math
import tracemalloc
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from analysis_support import _rows

import dob_hil.log.reader as reader_module
from dob_hil.analysis.int_distribution import IntCounts
from dob_hil.analysis.loaded import ANALYSIS_FIELDS, load_log
from dob_hil.analysis.metrics import compute_metrics
from dob_hil.analysis.streamed import analyze_streamed
from dob_hil.commands import analyze as analyze_command
from dob_hil.log import LogData, LogWriter, read_log
from dob_hil.log.bench import write_synthetic

TINY_GROUP_BYTES = 4096  # every chunk its own group


def _same(a: Any, b: Any, where: str = "") -> None:
    """Equal, floats to 1e-12 relative (sums of squares are accumulated block by block)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), where
        for key in a:
            _same(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _same(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        assert (math.isnan(a) and math.isnan(b)) or a == pytest.approx(b, rel=1e-12, abs=0.0), where
    else:
        assert a == b, where


def rewrite_interleaved(
    data: LogData, path: Path, *, truth: np.ndarray | None = None, samples: np.ndarray | None = None
) -> Path:
    """``data`` written again in small chunks, each period's records together as a run writes them."""
    samples = data.samples if samples is None else samples
    truth = data.truth if truth is None else truth
    rows, truth_rows, frame_rows = _rows(samples), _rows(truth), _rows(data.frames)
    per = max(1, -(-len(frame_rows) // max(len(rows), 1)))
    with LogWriter(
        path, data.layout, metadata={"run": data.metadata["run"]}, attachments=data.attachments,
        chunk_size_bytes=2048,
    ) as log:  # fmt: skip
        for i, row in enumerate(rows):
            log.sample(*row)
            for ts, aid, direction, dlc, flags, payload in frame_rows[i * per : (i + 1) * per]:
                length = 0 if flags & 0x04 else min(dlc, 8)
                log.frame_raw(ts, aid, direction == 0, dlc, bytes(payload[:length]), flags)
            if i < len(truth_rows):
                log.truth(*truth_rows[i])
            log.flush()
        for row in truth_rows[len(rows) :]:
            log.truth(*row)
        for ev in data.events:
            log.event(ev["time_ns"], ev["level"], ev["kind"], ev["message"], ev.get("data"))
        log.flush(force=True)
    return path


def _in_memory(path: Path, from_s: float) -> dict[str, Any]:
    return compute_metrics(load_log(path, fields=ANALYSIS_FIELDS), from_s)


@pytest.mark.parametrize("scenario", ["paper-sine", "paper-step"])
def test_streamed_metrics_equal_the_in_memory_ones_over_many_groups(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, scenario: str
) -> None:
    path = rewrite_interleaved(read_log(runs[(scenario, True)]), tmp_path / "many.mcap")
    monkeypatch.setattr(reader_module, "GROUP_BYTES", TINY_GROUP_BYTES)
    chunks = read_log(path).metadata  # the file is read whole once: it must hold many chunks
    assert chunks is not None
    for from_s in (0.0, 0.1, 10.0):
        expected = _in_memory(path, from_s)
        _, got = analyze_streamed(path, from_s)
        _same(expected, got)
    assert expected["samples"] == 0  # --from past the end: the same warning
    _, got = analyze_streamed(path, 0.0)
    assert got["truth_samples"] == got["samples"] > 900 and got["bus_load"] is not None
    assert got["timing_percentiles"] == "exact"


@pytest.mark.parametrize("lose_truth", [False, True])
def test_streamed_finds_the_truth_offset_of_a_realtime_log(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, lose_truth: bool
) -> None:
    """Truth counted 300 periods ahead of the host (as in real time): offset 0 fails its check,
    the streamed search finds 300 as match_truth does; also with truth records lost (period
    indexes not consecutive: the index is held)."""
    data = read_log(runs[("paper-sine", True)])
    samples, truth = data.samples.copy(), data.truth.copy()
    samples["feedback_seq"] = (samples["seq"].astype(np.int64) + 300) % 256
    truth["period_index"] += 300
    if lose_truth:
        truth = np.delete(truth, np.arange(400, 410))
    path = rewrite_interleaved(data, tmp_path / "rt.mcap", samples=samples, truth=truth)
    monkeypatch.setattr(reader_module, "GROUP_BYTES", TINY_GROUP_BYTES)
    expected = _in_memory(path, 0.0)
    _, got = analyze_streamed(path, 0.0)
    _same(expected, got)
    assert got["truth_samples"] == got["samples"] - (10 if lose_truth else 0)


def test_long_log_is_streamed_by_the_command(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    path = runs[("paper-sine", True)]
    other = runs[("paper-sine", False)]
    expected = analyze_command.analyze_logs(
        [path, other], from_s=0.0, plots_dir=None, as_json=True, plots=False
    )
    capsys.readouterr()
    monkeypatch.setattr(analyze_command, "STREAM_ABOVE_SAMPLES", 10)
    called: list[Path] = []
    from dob_hil.analysis import streamed

    real = streamed.survey
    monkeypatch.setattr(streamed, "survey", lambda p, f: called.append(p) or real(p, f))
    got = analyze_command.analyze_logs([path, other], from_s=0.0, plots_dir=None, as_json=True, plots=False)
    assert called == [path, other]
    assert json.loads(capsys.readouterr().out) == got
    _same(expected, got)


def test_int_counts_give_numpys_percentiles() -> None:
    rng = np.random.default_rng(7)
    for _ in range(300):
        n = int(rng.integers(1, 400))
        values = rng.integers(0, int(rng.choice([3, 1000, 10**9])), n)
        counts = IntCounts()
        for part in np.array_split(values, int(rng.integers(1, 6))):
            counts.add(part)
        scaled = values.astype(np.float64) * 1e-3
        p50, p99 = np.percentile(scaled, [50.0, 99.0])
        assert counts.distribution(1e-3) == {"p50": p50, "p99": p99, "max": scaled.max(), "n": n}
        assert counts.median() == float(np.median(values))


def test_int_counts_coarsen_beyond_their_bound(monkeypatch: pytest.MonkeyPatch) -> None:
    import dob_hil.analysis.int_distribution as module

    monkeypatch.setattr(module, "MAX_DISTINCT", 1000)
    values = np.arange(1, 200_001, dtype=np.int64) * 7
    counts = IntCounts()
    for part in np.array_split(values, 20):
        counts.add(part)
    assert counts.coarse and counts.n == len(values) and len(counts.values) <= 20 * 4096
    p50, p99 = np.percentile(values.astype(np.float64), [50.0, 99.0])
    d = counts.distribution()
    assert d is not None
    for got, want in ((d["p50"], p50), (d["p99"], p99), (d["max"], values.max())):
        assert want * (1 - 2.0**-11) - 1 <= got <= want  # rounded down to 12 significant bits


def _peak_bytes(fn: Any) -> int:
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_streamed_memory_does_not_grow_with_the_log(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Peak traced memory for a log 4x as long: the in-memory path grows with the samples, the
    streamed one only by the file's chunk map (about 1 KB per 256 KiB chunk). The reader's
    read-ahead (a constant 32 MiB, filled more or less depending on the threads' timing) is cut
    to one chunk, so that both logs exceed it and the peak does not depend on timing. The timing
    distributions are held at a small bound (they grow with the distinct values seen, up to
    MAX_DISTINCT, then stay within the coarse bins)."""
    import dob_hil.analysis.int_distribution as distribution

    monkeypatch.setattr(reader_module, "GROUP_BYTES", 256 << 10)
    monkeypatch.setattr(reader_module, "READ_AHEAD_BYTES", 0)  # one chunk in flight (32 MiB by default)
    monkeypatch.setattr(distribution, "MAX_DISTINCT", 512)
    monkeypatch.setattr(distribution, "COARSE_BITS", 6)
    short, long = tmp_path / "short.mcap", tmp_path / "long.mcap"
    # chunks by size only (256 KiB), not by time: their number must not depend on the machine's load
    write_synthetic(short, 10_000, chunk_interval_ns=3600 * 10**9)
    write_synthetic(long, 40_000, chunk_interval_ns=3600 * 10**9)
    analyze_streamed(short, 0.0)  # imports and caches outside the measurement
    streamed = [_peak_bytes(lambda p=p: analyze_streamed(p, 0.0)) for p in (short, long)]
    in_memory = [_peak_bytes(lambda p=p: _in_memory(p, 0.0)) for p in (short, long)]
    growth_in_memory = in_memory[1] - in_memory[0]
    assert growth_in_memory > 30_000 * 200  # the arrays: at least 200 B per extra sample
    # 5 % of the in-memory growth: about 13 B per extra sample (two int64 columns would break it)
    assert streamed[1] - streamed[0] < 0.05 * growth_in_memory, (streamed, in_memory)
    assert streamed[1] < in_memory[1] / 2


def test_streamed_per_axis_metrics_of_a_two_by_two_log(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Per-output and per-input lists (n_outputs, n_inputs columns) equal the in-memory ones."""
    from mimo_log_support import write_mimo_log

    run = write_mimo_log(tmp_path / "mimo.mcap", dob=True)
    path = rewrite_interleaved(read_log(run.path), tmp_path / "mimo-many.mcap")
    monkeypatch.setattr(reader_module, "GROUP_BYTES", TINY_GROUP_BYTES)
    expected = _in_memory(path, 0.0)
    _, got = analyze_streamed(path, 0.0)
    _same(expected, got)
    assert len(got["tracking_error_rms_per_output"]) == 2 and len(got["current_max_A_per_input"]) == 2
