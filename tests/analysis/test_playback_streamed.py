"""replay --to-bus streamed: a log in many groups of chunks played as the whole arrays would be.

The oracle is the whole-array computation (the frames read with ``read_log``, our echoes and the
error frames left out, classic and FD merged by a stable sort of their timestamps, the figures
from numpy's percentiles), as ``play_frames`` computed them before the playback was streamed.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path
from typing import Any

import can
import numpy as np
import numpy.typing as npt
import pytest
from analysis_support import Receiver

from dob_hil.analysis import playback
from dob_hil.analysis.frames import frame_messages
from dob_hil.analysis.int_distribution import IntCounts
from dob_hil.analysis.metrics import distribution
from dob_hil.analysis.playback import START_LEAD_NS, plan_playback, play_frames, play_log
from dob_hil.cli import main
from dob_hil.errors import DriveFault, LogReadError
from dob_hil.log import LogData, read_log
from dob_hil.log.schemas import CAN_FLAG_ERROR, CAN_FLAG_EXTENDED, CAN_FLAG_FD, CAN_RX, CAN_TX

StructArray = npt.NDArray[np.void]
_channels = itertools.count()
GAP_NS = 61_000_000_000


def _log(
    path: Path, base: LogData, periods: int = 3000, gap_at: int | None = None, fd_bridge: bool = False
) -> Path:
    """``periods`` periods of 300 us in chunks of 2 KiB (many groups): a tx command (0x201), its
    udp_multicast echo, the feedback (0x181); every 10th period a 12-byte CAN FD frame from the
    drive (0x300), every 20th one of ours (0x310, at the feedback's timestamp: classic goes first)
    with its echo, every 50th an error frame. ``gap_at``: the periods from there on 61 s later
    (``fd_bridge``: an FD frame in the middle of the silence, so the log as a whole has no gap)."""
    from dob_hil.log import LogWriter

    with LogWriter(path, base.layout, metadata={"run": base.metadata["run"]}, chunk_size_bytes=2048) as log:
        for k in range(periods):
            t = 1_000_000_000 + k * 300_000 + (GAP_NS if gap_at is not None and k >= gap_at else 0)
            if fd_bridge and k == gap_at:
                log.frame_raw(t - GAP_NS // 2, 0x300, True, 12, bytes(12), CAN_FLAG_FD)
            log.frame_raw(t + 10, 0x201, False, 3, bytes([k & 0xFF, 1, 2]), 0)
            if k % 10 == 0:
                log.frame_raw(t + 15, 0x300, True, 12, bytes(range(12)), CAN_FLAG_FD)
            log.frame_raw(t + 20, 0x201, True, 3, bytes([k & 0xFF, 1, 2]), 0)  # our own echo
            if k % 50 == 0:
                log.frame_raw(t + 25, 0x20000004, True, 8, bytes(8), CAN_FLAG_ERROR | CAN_FLAG_EXTENDED)
            log.frame_raw(t + 30, 0x181, True, 6, bytes([1, 2, 3, 4, 5, k & 0xFF]), 0)
            if k % 20 == 0:
                log.frame_raw(t + 30, 0x310, False, 16, bytes(range(16)), CAN_FLAG_FD)
                log.frame_raw(t + 40, 0x310, True, 16, bytes(range(16)), CAN_FLAG_FD)  # its echo
            log.flush()
        log.flush(force=True)
    return path


@pytest.fixture
def base(runs: dict[tuple[str, bool], Path]) -> LogData:
    return read_log(runs[("paper-sine", False)])


@pytest.fixture
def many_groups(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Groups of 4 KiB; the blocks each stream of the playback yields, counted."""
    import dob_hil.log.reader as reader_module

    monkeypatch.setattr(reader_module, "GROUP_BYTES", 4096)
    blocks: list[int] = []
    real = playback.open_stream

    def counting(*args: Any, **kwargs: Any) -> Any:
        stream = real(*args, **kwargs)
        inner = stream.blocks

        def blocks_counted() -> Any:
            for b in inner():
                blocks.append(1)
                yield b

        stream.blocks = blocks_counted  # type: ignore[method-assign]
        return stream

    monkeypatch.setattr(playback, "open_stream", counting)
    return blocks


def _kept(frames: StructArray, direction: int | None) -> tuple[StructArray, int, int]:
    """The old whole-array selection of one channel: (sent, errors, echoes); our ids log-wide."""
    tx_ids = np.unique(frames["arbitration_id"][frames["direction"] == CAN_TX])
    if direction is not None:
        frames = frames[frames["direction"] == direction]
    error = (frames["flags"] & CAN_FLAG_ERROR) != 0
    echo = ~error & (frames["direction"] == CAN_RX) & np.isin(frames["arbitration_id"], tx_ids)
    return frames[~(error | echo)], int(error.sum()), int(echo.sum())


def _expected(path: Path, direction: int | None = None) -> tuple[list[can.Message], int, int]:
    data = read_log(path)
    classic, errors, echoes = _kept(data.frames, direction)
    fd, fd_errors, fd_echoes = _kept(data.fd_frames, direction)
    return list(frame_messages(classic, fd)), errors + fd_errors, echoes + fd_echoes


def _key(m: can.Message) -> tuple[int, bytes, bool]:
    return (m.arbitration_id, bytes(m.data), m.is_fd)


def _old_gaps(expected: list[can.Message]) -> tuple[int, dict[str, float | int] | None]:
    """The most frequent id (the smallest of equals) and its recorded gaps, from the whole arrays."""
    ids = np.asarray([m.arbitration_id for m in expected])
    stamps = np.asarray([round(m.timestamp * 1e9) for m in expected], dtype=np.int64)
    values, counts = np.unique(ids, return_counts=True)
    gap_id = int(values[np.argmax(counts)])
    return gap_id, distribution(np.diff(stamps[ids == gap_id]), 1e-3)


@pytest.mark.parametrize("direction", ["both", "rx", "tx"])
def test_streamed_to_bus_sends_the_whole_array_order(
    base: LogData, tmp_path: Path, many_groups: list[int], capsys: pytest.CaptureFixture[str], direction: str
) -> None:
    path = _log(tmp_path / "mixed.mcap", base)
    want = {"both": None, "rx": CAN_RX, "tx": CAN_TX}[direction]
    expected, errors, echoes = _expected(path, want)
    channel = f"dob-hil-streamed-{next(_channels)}"
    receiver = Receiver(channel, len(expected))
    receiver.start()
    argv = [
        "replay",
        str(path),
        "--to-bus",
        "-i",
        "virtual",
        "-c",
        channel,
        "--json",
        "--direction",
        direction,
    ]
    assert main(argv) == 0
    receiver.join(30.0)
    assert len(many_groups) > 30  # streamed over many groups of chunks, each pass
    assert [_key(m) for m in receiver.got] == [_key(m) for m in expected]
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"mode", "log", *playback.PlaybackStats.__dataclass_fields__}
    assert (out["frames_sent"], out["skipped_error_frames"], out["skipped_own_echoes"]) == (
        len(expected), errors, echoes
    )  # fmt: skip
    if want is None:  # 3000 commands, 3000 feedbacks, 300 + 150 FD frames; 60 errors, 3000 + 150 echoes
        assert (len(expected), errors, echoes) == (6450, 60, 3150)
        assert sum(m.is_fd for m in receiver.got) == 450
    if want == CAN_RX:  # the drive's frames only: none of our commands or their echoes
        assert {m.arbitration_id for m in receiver.got} == {0x181, 0x300}
    gap_id, recorded = _old_gaps(expected)
    assert out["gap_id"] == gap_id and out["recorded_gap_us"] == recorded
    assert out["sent_gap_us"]["n"] == recorded["n"] if recorded else out["sent_gap_us"] is None
    assert out["lateness_us"]["n"] == len(expected)
    duration = (expected[-1].timestamp - expected[0].timestamp) if expected else 0.0
    assert out["duration_s"] == pytest.approx(duration, abs=1e-9)


class FakeClock:
    """A clock that moves only when slept on and by a fixed cost per send; the sends recorded."""

    def __init__(self, send_cost_ns: int, refuse_at: int | None = None) -> None:
        self.now = 10_000_000
        self.send_cost_ns = send_cost_ns
        self.refuse_at = refuse_at
        self.sent: list[tuple[int, can.Message]] = []

    def clock_ns(self) -> int:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += round(seconds * 1e9)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if len(self.sent) == self.refuse_at:
            raise can.CanOperationError("buffer full")
        self.sent.append((self.now, msg))
        self.now += self.send_cost_ns


def test_streamed_and_array_playback_report_the_whole_array_figures(
    base: LogData, tmp_path: Path, many_groups: list[int], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A fake clock (sends cost 200 us: the two or three frames of a 300 us period fall behind, many late):
    every figure of the report equals the one computed from the whole arrays, across many flushes
    of the figures' buffers, from the log streamed and from the arrays."""
    monkeypatch.setattr(playback, "FLUSH", 97)
    monkeypatch.setattr(playback, "ROWS", 50)
    path = _log(tmp_path / "mixed.mcap", base, periods=1000)
    expected, errors, echoes = _expected(path)
    reports = []
    for play in ("log", "arrays"):
        clock = FakeClock(send_cost_ns=200_000)
        options: dict[str, Any] = {"clock_ns": clock.clock_ns, "sleep": clock.sleep, "spin_ns": 0}
        if play == "log":
            stats = play_log(clock, path, **options)  # type: ignore[arg-type]
        else:
            data = read_log(path)
            stats = play_frames(clock, data.frames, data.fd_frames, **options)  # type: ignore[arg-type]
        assert [_key(m) for _, m in clock.sent] == [_key(m) for m in expected]
        stamps = np.asarray([round(m.timestamp * 1e9) for m in expected], dtype=np.int64)
        sent_at = np.asarray([t for t, _ in clock.sent], dtype=np.int64)
        lateness = sent_at - (10_000_000 + START_LEAD_NS + stamps - stamps[0])
        assert lateness.min() >= 0 and np.count_nonzero(lateness > 1_000_000) > 0
        gap_id, recorded = _old_gaps(expected)
        ids = np.asarray([m.arbitration_id for m in expected])
        assert stats.to_dict() == {
            "frames_sent": len(expected),
            "skipped_error_frames": errors,
            "skipped_own_echoes": echoes,
            "duration_s": (stamps[-1] - stamps[0]) * 1e-9,
            "late_frames": int(np.count_nonzero(lateness > 1_000_000)),
            "late_threshold_us": 1000.0,
            "lateness_us": distribution(lateness, 1e-3),
            "gap_id": gap_id,
            "recorded_gap_us": recorded,
            "sent_gap_us": distribution(np.diff(sent_at[ids == gap_id]), 1e-3),
        }
        reports.append(stats)
    assert reports[0] == reports[1]


def test_a_long_gap_is_refused_before_the_bus_is_opened(
    base: LogData, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import dob_hil.link.bus as bus_module
    import dob_hil.log.reader as reader_module

    def no_bus(*args: object, **kwargs: object) -> None:
        raise AssertionError("the bus was opened")

    monkeypatch.setattr(bus_module, "open_bus", no_bus)
    monkeypatch.setattr(reader_module, "GROUP_BYTES", 4096)  # the gap checked across many blocks
    path = _log(tmp_path / "gap.mcap", base, periods=300, gap_at=150)
    data = read_log(path)
    stamps = np.sort(np.concatenate([data.frames["timestamp_ns"], data.fd_frames["timestamp_ns"]]))
    i = int(np.argmax(np.diff(stamps.astype(np.int64))))  # the old whole-array check's frame
    assert main(["replay", str(path), "--to-bus", "-i", "virtual", "-c", "never"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"dob-hil replay: error: replay --to-bus: frames {i} and {i + 1} (in time order) are "
        "61.0003 s apart, more than the 60 s a recording can hold; refusing to replay this log"
    ]
    for direction in ("rx", "tx"):  # in each direction too
        assert (
            main(["replay", str(path), "--to-bus", "-i", "virtual", "-c", "x", "--direction", direction]) == 2
        )
        assert "refusing to replay" in capsys.readouterr().err
    monkeypatch.setattr(playback, "FLUSH", 97)  # array blocks of 97 frames
    with pytest.raises(LogReadError, match=f"frames {i} and {i + 1} .* refusing to replay"):
        play_frames(FakeClock(0), data.frames, data.fd_frames)  # type: ignore[arg-type]


def test_the_gap_is_in_time_order_across_channels_and_among_the_frames_sent(
    base: LogData, tmp_path: Path
) -> None:
    """An FD frame in the middle of a classic silence closes the gap, unless it is not sent."""
    path = _log(tmp_path / "bridged.mcap", base, periods=300, gap_at=150, fd_bridge=True)
    source = playback.LogFrames(path)
    assert plan_playback(source).refusal is None
    plan = plan_playback(source, CAN_TX)  # the bridging FD frame is the drive's: not sent
    assert plan.refusal is not None and "refusing to replay" in str(plan.refusal)


def test_no_frames_nothing_sent(
    base: LogData, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import dob_hil.link.bus as bus_module
    from dob_hil.log import LogWriter

    monkeypatch.setattr(bus_module, "open_bus", lambda *a, **k: pytest.fail("the bus was opened"))
    path = tmp_path / "rx-only.mcap"
    with LogWriter(path, base.layout, metadata={"run": base.metadata["run"]}) as log:
        log.frame_raw(1_000, 0x181, True, 2, b"\x01\x02", 0)
    assert main(["replay", str(path), "--to-bus", "-i", "virtual", "-c", "x", "--direction", "tx"]) == 0
    assert capsys.readouterr().err == f"dob-hil replay: {path}: the log holds no frames; nothing sent\n"


def test_a_refused_send_is_a_drive_fault(base: LogData, tmp_path: Path) -> None:
    path = _log(tmp_path / "mixed.mcap", base, periods=40)
    expected, _, _ = _expected(path)
    clock = FakeClock(0, refuse_at=7)
    with pytest.raises(DriveFault, match=f"sending frame 7 \\(id 0x{expected[7].arbitration_id:X}\\) failed"):
        play_log(clock, path, clock_ns=clock.clock_ns, sleep=clock.sleep, spin_ns=0)  # type: ignore[arg-type]
    assert len(clock.sent) == 7


@pytest.mark.parametrize("seed", range(8))
def test_time_order_merges_blocks_as_a_sort_of_the_union(seed: int) -> None:
    """The plan pass's vectorised merge: channels cut into random blocks (empty ones too, one
    channel sometimes empty) come out as the sorted union, each frame with its own flag."""
    rng = np.random.default_rng(seed)

    def channel(n: int, tag: int) -> tuple[list[Any], npt.NDArray[np.uint64]]:
        t = np.sort(rng.integers(0, 5000, size=n)).astype(np.uint64)
        cuts = np.sort(rng.integers(0, n + 1, size=int(rng.integers(0, 12))))
        return [(b, np.full(len(b), tag == 1)) for b in np.split(t, cuts)], t

    a, ta = channel(int(rng.integers(0, 400)) if seed % 4 else 0, 0)
    b, tb = channel(int(rng.integers(0, 400)), 1)
    out = list(playback.time_order(iter(a), iter(b)))
    t = np.concatenate([np.zeros(0, np.uint64), *(o[0] for o in out)])
    flags = np.concatenate([np.zeros(0, bool), *(o[1] for o in out)])
    union = np.concatenate([ta, tb])
    assert np.array_equal(t, np.sort(union))
    assert np.array_equal(np.sort(t[flags]), tb) and np.array_equal(np.sort(t[~flags]), ta)


@pytest.mark.parametrize("seed", range(6))
def test_int_counts_give_numpys_percentiles(seed: int) -> None:
    """The streamed figures (IntCounts, added block by block) are metrics.distribution's."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 5000))
    values = rng.integers(0, [50, 10**4, 10**9][seed % 3], size=n)
    counts = IntCounts()
    for block in np.array_split(values, 7):
        counts.add(block)
    assert counts.distribution(1e-3) == distribution(values, 1e-3)
