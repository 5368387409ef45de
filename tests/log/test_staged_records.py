"""Lockstep's staged records (dob_hil.log.writer, module docstring): the frame hook and the truth
sink queue their records and the owner thread packs them in runs. The file must hold the same
records as packing each one at once, in their order per channel, with every sequence number, and
the queue must stay short however long the run."""

from __future__ import annotations

import os
import threading
from pathlib import Path

import can
import numpy as np
import pytest
from log_checks import CallClock

from dob_hil.log import LogLayout, LogWriteError, LogWriter, read_log
from dob_hil.log.check import assert_complete
from dob_hil.log.schemas import CAN_RX, CAN_TX
from dob_hil.log.writer import STAGE_BYTES, message_flags

LAYOUT = LogLayout(2, 1, 1, 2)
PERIOD_NS = 300_000


def _sample(log: LogWriter, k: int) -> None:
    t = k * PERIOD_NS
    log.sample(
        t, t, t, 0, (k,), (0.5 * k,), (1.0, 2.0), (1.0, 2.0), (1.0, 2.0), (0.1,), (0.2,), (0.3,), (0.3,), k,
        100, (300,), k % 256, 0,
    )  # fmt: skip


def _period_frames(k: int) -> list[tuple[can.Message, bool]]:
    """A period's frames, a few of the general path's kinds among them."""
    frames = [
        (can.Message(arbitration_id=0x80, data=b"", is_extended_id=False), False),
        (can.Message(arbitration_id=0x181, data=k.to_bytes(6, "little"), is_extended_id=False), True),
        (
            can.Message(arbitration_id=0x201, data=(k % 977).to_bytes(4, "little"), is_extended_id=False),
            False,
        ),
    ]
    if k % 7 == 0:
        frames.append((can.Message(arbitration_id=0x1ABCDEF, data=b"\x01", is_extended_id=True), True))
    if k % 11 == 0:
        frames.append(
            (can.Message(arbitration_id=0x7FF, is_remote_frame=True, dlc=8, is_extended_id=False), False)
        )
    if k % 13 == 0:
        data = bytes(range(12))
        frames.append((can.Message(arbitration_id=0x123, data=data, is_fd=True, is_extended_id=False), True))
    return frames


def _truth(k: int) -> tuple[int, int, tuple[float, float], float, float, int]:
    return (k, k * PERIOD_NS, (0.001 * k, -0.5 * k), 0.01 * k, 0.25, 1)


def test_staged_records_read_back_as_those_packed_at_once(tmp_path: Path) -> None:
    n = 3000  # several runs of staged records, and a hand-over or two
    staged_path, direct_path = tmp_path / "staged.mcap", tmp_path / "direct.mcap"
    now = [0]
    with LogWriter(staged_path, LAYOUT) as log:
        hook, sink = log.clocked_frame_hook(CallClock(lambda: now[0])), log.truth_hook()
        for k in range(n):
            now[0] = k * PERIOD_NS
            for msg, is_rx in _period_frames(k):
                hook(msg, is_rx)
            sink(_truth(k))
            _sample(log, k)
            if k % 1000 == 999:
                log.flush(force=True)
    with LogWriter(direct_path, LAYOUT) as log:
        for k in range(n):
            t = k * PERIOD_NS
            for msg, is_rx in _period_frames(k):
                log.frame_raw(t, msg.arbitration_id, is_rx, msg.dlc, msg.data or b"", message_flags(msg))
            k_, time_ns, state, d, a, drive_state = _truth(k)
            log.truth(time_ns, state, (d,), (a,), k_, drive_state)
            _sample(log, k)
    staged, direct = read_log(staged_path), read_log(direct_path)
    assert staged.complete and not staged.warnings
    assert len(staged.samples) == n and len(staged.truth) == n
    assert len(staged.frames) == sum(len(_period_frames(k)) for k in range(n)) - len(staged.fd_frames)
    for kind in ("samples", "frames", "fd_frames", "truth"):
        a, b = getattr(staged, kind), getattr(direct, kind)
        for name in a.dtype.names or ():
            assert np.array_equal(a[name], b[name]), (kind, name)
    assert_complete(staged_path)  # every sequence number of every channel, none twice


def test_the_stage_stays_short_in_a_long_run() -> None:
    with LogWriter(os.devnull, LAYOUT) as log:
        hook, sink = log.clocked_frame_hook(CallClock(lambda: 0)), log.truth_hook()
        longest = 0
        for k in range(20_000):
            for msg, is_rx in _period_frames(k)[:3]:
                hook(msg, is_rx)
            sink(_truth(k))
            _sample(log, k)
            longest = max(longest, len(log._staged_frames))
        # packed each time the batch grew by STAGE_BYTES of samples: a run of some 90 periods
        periods = STAGE_BYTES // log._sample_len + 2
        assert 0 < longest <= 3 * periods
        assert len(log._staged_truth) <= periods
    assert log.stats.enqueued_records == 20_000 * 5


def test_frames_staged_by_another_thread_keep_their_order_and_times_never_step_back(tmp_path: Path) -> None:
    path = tmp_path / "threads.mcap"
    times = iter([5_000, 4_000, 6_000])  # the other thread read the clock before the first frame
    with LogWriter(path, LAYOUT) as log:
        hook = log.clocked_frame_hook(CallClock(lambda: next(times)))
        hook(can.Message(arbitration_id=0x601, data=b"\x40\x00\x10\x00", is_extended_id=False), False)
        other = threading.Thread(
            target=hook, args=(can.Message(arbitration_id=0x581, data=b"\x43", is_extended_id=False), True)
        )
        other.start()
        other.join()
        hook(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False), False)
    frames = read_log(path).frames
    assert list(frames["arbitration_id"]) == [0x601, 0x581, 0x80]
    assert list(frames["timestamp_ns"]) == [5_000, 5_000, 6_000]
    assert list(frames["direction"]) == [CAN_TX, CAN_RX, CAN_TX]


def test_a_staged_frame_that_cannot_be_logged_is_named() -> None:
    log = LogWriter(os.devnull, LAYOUT)
    hook = log.clocked_frame_hook(CallClock(lambda: 0))
    hook(can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False), True)
    hook(can.Message(arbitration_id=0x181, data=bytes(65), is_fd=True, is_extended_id=False), True)
    hook(can.Message(arbitration_id=0x182, data=b"\x02", is_extended_id=False), True)
    hook(can.Message(arbitration_id=0x183, data=b"\x03", is_extended_id=False), True)
    with pytest.raises(LogWriteError, match="65 data bytes"):
        log.flush(force=True)
    assert log._seq_can == 1  # the frame before it was packed
    # the frames after it stay staged, in their order, and are packed by the next hand-over
    assert [msg.arbitration_id for _, msg, _ in log._staged_frames] == [0x182, 0x183]
    log._pack_staged()
    assert log._seq_can == 3 and not log._staged_frames


def test_a_staged_truth_that_cannot_be_logged_leaves_the_rest_staged() -> None:
    log = LogWriter(os.devnull, LAYOUT)
    sink = log.truth_hook()
    sink(_truth(0))
    sink((1, PERIOD_NS, (0.1, 0.2), 0.0, 0.25, "not a drive state"))
    sink(_truth(2))
    with pytest.raises(LogWriteError, match="truth"):
        log.flush(force=True)
    assert log._seq_truth == 1
    assert [t[0] for t in log._staged_truth] == [2]
    log._pack_staged()
    assert log._seq_truth == 2 and not log._staged_truth


def test_close_packs_what_is_staged(tmp_path: Path) -> None:
    path = tmp_path / "close.mcap"
    with LogWriter(path, LAYOUT) as log:
        hook, sink = log.clocked_frame_hook(CallClock(lambda: 7)), log.truth_hook()
        hook(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False), False)
        sink(_truth(0))
        assert log.stats.enqueued_records == 0  # still staged
    data = read_log(path)
    assert len(data.frames) == 1 and len(data.truth) == 1 and data.complete


def test_a_malformed_staged_truth_keeps_the_counts_of_those_packed_before_it() -> None:
    log = LogWriter(os.devnull, LAYOUT)
    sink = log.truth_hook()
    sink(_truth(0))
    sink(_truth(1))
    sink((2, 2 * PERIOD_NS))  # not a ground-truth tuple: the general path refuses it
    sink(_truth(3))
    with pytest.raises(ValueError):
        log.flush(force=True)
    assert log._seq_truth == 2 and log._batch_records == 2  # the two before it are in the batch
    assert [t[0] for t in log._staged_truth] == [3]
    log._pack_staged()
    assert log._seq_truth == 3 and log._batch_records == 3 and not log._staged_truth
