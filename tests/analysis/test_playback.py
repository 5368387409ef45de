"""replay --to-bus: the recorded frames onto python-can's virtual bus, received by another thread."""

from __future__ import annotations

import itertools
import json
import os
from pathlib import Path

import can
import numpy as np
import pytest
from analysis_support import Receiver

from dob_hil.analysis.bus_usage import counted_frames
from dob_hil.analysis.frames import frame_messages
from dob_hil.analysis.playback import START_LEAD_NS, play_frames
from dob_hil.cli import main
from dob_hil.link.protocol import FrameKind, split_id
from dob_hil.log import read_log

_channels = itertools.count()


def _expected(path: Path) -> list[can.Message]:
    data = read_log(path)
    return list(frame_messages(data.frames[counted_frames(data.frames)], data.fd_frames))


def _same(got: list[can.Message], expected: list[can.Message]) -> None:
    assert [(m.arbitration_id, bytes(m.data), m.is_extended_id) for m in got] == [
        (m.arbitration_id, bytes(m.data), m.is_extended_id) for m in expected
    ]


def test_play_frames_onto_a_virtual_bus(runs: dict[tuple[str, bool], Path]) -> None:
    path = runs[("paper-step", True)]
    expected = _expected(path)
    channel = f"dob-hil-playback-{next(_channels)}"
    receiver = Receiver(channel, len(expected))
    receiver.start()
    with can.Bus(interface="virtual", channel=channel, receive_own_messages=False) as bus:
        data = read_log(path)
        stats = play_frames(bus, data.frames, data.fd_frames)
    receiver.join(15.0)
    _same(receiver.got, expected)
    assert stats.frames_sent == len(expected)
    assert stats.duration_s == pytest.approx(expected[-1].timestamp - expected[0].timestamp, abs=1e-6)


def test_replay_to_bus_command(
    runs: dict[tuple[str, bool], Path], capsys: pytest.CaptureFixture[str]
) -> None:
    path = runs[("paper-sine", False)]
    expected = _expected(path)
    channel = f"dob-hil-playback-{next(_channels)}"
    receiver = Receiver(channel, len(expected))
    receiver.start()
    assert main(["replay", str(path), "--to-bus", "-i", "virtual", "-c", channel, "--json"]) == 0
    receiver.join(15.0)
    _same(receiver.got, expected)
    out = json.loads(capsys.readouterr().out)
    assert out["frames_sent"] == len(expected) and out["skipped_error_frames"] == 0
    assert out["recorded_gap_us"]["p50"] == pytest.approx(300.0, abs=1.0)  # the 300 us feedback period
    assert out["sent_gap_us"]["n"] == out["recorded_gap_us"]["n"]


def test_replay_to_bus_takes_the_real_time_options(
    runs: dict[tuple[str, bool], Path], capsys: pytest.CaptureFixture[str]
) -> None:
    path = runs[("paper-step", False)]
    expected = _expected(path)
    channel = f"dob-hil-playback-{next(_channels)}"
    receiver = Receiver(channel, len(expected))
    receiver.start()
    argv = ["replay", str(path), "--to-bus", "-i", "virtual", "-c", channel, "--cpu", "0", "--sched-fifo"]
    assert main(argv) == 0
    receiver.join(15.0)
    _same(receiver.got, expected)
    captured = capsys.readouterr()
    assert "gap: recorded p50 300.0 us" in captured.out
    assert "lateness p50" in captured.out


def test_replay_to_bus_rx_only_stands_in_for_the_drive(
    runs: dict[tuple[str, bool], Path], capsys: pytest.CaptureFixture[str]
) -> None:
    """--direction rx sends only what the drive sent: no recorded command reaches a live bus."""
    path = runs[("paper-step", True)]
    data = read_log(path)
    n_rx = int(np.count_nonzero(counted_frames(data.frames) & (data.frames["direction"] == 0)))
    channel = f"dob-hil-playback-{next(_channels)}"
    receiver = Receiver(channel, n_rx)
    receiver.start()
    args = ["replay", str(path), "--to-bus", "-i", "virtual", "-c", channel, "--direction", "rx", "--json"]
    assert main(args) == 0
    receiver.join(15.0)
    assert len(receiver.got) == n_rx
    drive_kinds = (FrameKind.FAULT, FrameKind.FEEDBACK, FrameKind.HEARTBEAT)
    assert all(split_id(m.arbitration_id)[0] in drive_kinds for m in receiver.got)
    assert json.loads(capsys.readouterr().out)["frames_sent"] == n_rx


class FakeClock:
    """A clock that only moves when slept on, plus a fixed cost per send."""

    def __init__(self, send_cost_ns: int) -> None:
        self.now = 10_000_000
        self.send_cost_ns = send_cost_ns
        self.sent_at: list[int] = []

    def clock_ns(self) -> int:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += round(seconds * 1e9)


class FakeBus:
    def __init__(self, clock: FakeClock) -> None:
        self.clock = clock

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.clock.sent_at.append(self.clock.now)
        self.clock.now += self.clock.send_cost_ns


def test_absolute_deadlines_do_not_drift(runs: dict[tuple[str, bool], Path]) -> None:
    """Each frame goes out at start + its recorded offset, whatever the sends cost; a frame whose
    deadline has passed goes out at once and is counted late."""
    data = read_log(runs[("paper-step", False)])
    ts = np.sort(data.frames["timestamp_ns"][counted_frames(data.frames)].astype(np.int64))
    clock = FakeClock(send_cost_ns=20_000)
    stats = play_frames(
        FakeBus(clock),
        data.frames,
        data.fd_frames,  # type: ignore[arg-type]
        clock_ns=clock.clock_ns,
        sleep=clock.sleep,
        spin_ns=0,  # the fake clock moves only in sleep(); spinning is tested below
    )
    sent = np.asarray(clock.sent_at)
    start = 10_000_000 + START_LEAD_NS
    # frames sharing a timestamp queue behind each other by the send cost; nothing goes out early
    assert np.all(sent >= start + (ts - ts[0]))
    gaps = np.diff(ts)
    on_time = np.concatenate([[True], gaps >= 20_000])
    assert np.array_equal(sent[on_time], (start + ts - ts[0])[on_time])
    assert stats.late_frames == 0 and stats.frames_sent == len(ts)


class TickingClock:
    """A clock that advances 1 us per reading; sleep() overshoots by 80 us (as Linux's timer slack)."""

    def __init__(self) -> None:
        self.now = 10_000_000
        self.sleeps: list[float] = []
        self.sent_at: list[int] = []
        self.send_cost_ns = 0

    def clock_ns(self) -> int:
        self.now += 1_000
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += round(seconds * 1e9) + 80_000


def test_sleep_then_spin_sends_on_the_deadline_despite_a_late_waking_sleep(
    runs: dict[tuple[str, bool], Path],
) -> None:
    data = read_log(runs[("paper-step", False)])
    frames = data.frames[:40]
    clock = TickingClock()
    stats = play_frames(FakeBus(clock), frames, None, clock_ns=clock.clock_ns, sleep=clock.sleep,  # type: ignore[arg-type]
                        spin_ns=150_000)  # fmt: skip
    lat = stats.lateness_us
    assert lat is not None and lat["max"] <= 10.0  # a few clock readings (1 us each) per frame
    assert stats.late_frames == 0
    naive = TickingClock()
    late = play_frames(FakeBus(naive), frames, None, clock_ns=naive.clock_ns, sleep=naive.sleep,  # type: ignore[arg-type]
                       spin_ns=0)  # fmt: skip
    assert late.lateness_us is not None and late.lateness_us["p50"] >= 80.0  # the sleep's overshoot


def test_replay_to_bus_leaves_the_process_as_it_found_it(runs: dict[tuple[str, bool], Path]) -> None:
    path = runs[("paper-step", False)]
    cpus, policy = os.sched_getaffinity(0), os.sched_getscheduler(0)
    channel = f"dob-hil-playback-{next(_channels)}"
    assert main(["replay", str(path), "--to-bus", "-i", "virtual", "-c", channel, "--cpu", "0",
                 "--sched-fifo", "--json"]) == 0  # fmt: skip
    assert os.sched_getaffinity(0) == cpus and os.sched_getscheduler(0) == policy
