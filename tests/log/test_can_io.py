"""python-can reads and writes dob_hil's MCAP through its plugin entry points (public API only)."""

from __future__ import annotations

import random
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import can
import pytest

from dob_hil.cli import main
from dob_hil.log import LogLayout, LogWriter, read_log, run_metadata

FRAMES = [
    can.Message(arbitration_id=0x123, data=b"\x01\x02\x03", is_extended_id=False, is_rx=True),
    can.Message(arbitration_id=0x1ABCDE, data=b"", is_extended_id=True, is_remote_frame=True, dlc=4),
    can.Message(arbitration_id=0x7FF, data=bytes(range(8)), is_extended_id=False, is_rx=False),
    can.Message(
        arbitration_id=0x456, data=bytes(range(24)), is_extended_id=False, is_fd=True, bitrate_switch=True
    ),
    can.Message(arbitration_id=0x20000080, is_error_frame=True, dlc=8, data=bytes(8)),
]


def _capture(path: Path, t0_s: float) -> list[can.Message]:
    sent = []
    with can.Logger(str(path)) as logger:
        for i, frame in enumerate(FRAMES):
            msg = frame.__copy__()
            msg.timestamp = t0_s + i * 0.001
            logger.on_message_received(msg)
            sent.append(msg)
    return sent


def test_logger_and_logreader_round_trip_every_kind_of_frame(tmp_path: Path) -> None:
    path = tmp_path / "capture.mcap"
    t0 = 1_790_000_000.25
    sent = _capture(path, t0)
    got = list(can.LogReader(str(path)))
    assert len(got) == len(sent)
    for g, s in zip(got, sent, strict=True):
        assert g.equals(s, timestamp_delta=1e-9, check_channel=False, check_direction=True), (g, s)


def test_log_time_is_non_decreasing_per_channel_even_when_stamps_go_back(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    path = tmp_path / "capture.mcap"
    with can.Logger(str(path)) as logger:
        for ts in (100.0, 100.002, 100.001, 100.003):  # one frame stamped before its predecessor
            logger.on_message_received(can.Message(timestamp=ts, arbitration_id=1, is_extended_id=False))
    with path.open("rb") as f:
        times = [m.log_time for _, _, m in make_reader(f).iter_messages(log_time_order=False)]
    assert times == sorted(times)
    stamps = [m.timestamp for m in can.LogReader(str(path))]
    assert sorted(stamps) == pytest.approx([100.0, 100.001, 100.002, 100.003])


def test_capture_opens_in_dob_hil_export_and_read_log(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "capture.mcap"
    sent = _capture(path, 1_790_000_000.0)
    data = read_log(path)
    assert len(data.frames) + len(data.fd_frames) == len(sent) and not data.warnings
    assert data.metadata["run"]["mode"] == "capture"
    out = tmp_path / "capture.asc"
    assert main(["export", str(path), "--format", "asc", "--out", str(out)]) == 0
    assert "2026" in out.read_text().splitlines()[0]  # the capture's own wall-clock date (Sept 2026)
    got = list(can.ASCReader(str(out)))
    assert [m.is_error_frame for m in got] == [m.is_error_frame for m in sent]
    # ASC writes an error frame without its id
    assert [m.arbitration_id for m in got if not m.is_error_frame] == [
        m.arbitration_id for m in sent if not m.is_error_frame
    ]


START_WALL_NS = 1_790_000_000 * 10**9


def _run_log_with_echoes(log: Path) -> None:
    """A lockstep-like run log (simulated time from 0) whose commands were echoed back."""
    start_wall_ns = START_WALL_NS
    layout = LogLayout(2, 1, 1, 2)
    meta = run_metadata(mode="lockstep", bus="virtual", period_ns=300_000, layout=layout,
                        start_wall_time_ns=start_wall_ns)  # fmt: skip
    with LogWriter(log, layout, metadata={"run": meta}) as writer:
        for k in range(10):
            writer.frame_raw(k * 300_000, 0x181, True, 6, bytes(6), 0)  # feedback from the drive
            writer.frame_raw(k * 300_000 + 1000, 0x201, False, 3, bytes(3), 0)  # our command
            writer.frame_raw(k * 300_000 + 1500, 0x201, True, 3, bytes(3), 0)  # its echo
        writer.close({})


def test_export_puts_a_run_log_on_the_wall_clock_without_echoes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "run.mcap"
    _run_log_with_echoes(log)
    out = tmp_path / "run.asc"
    assert main(["export", str(log), "--format", "asc", "--out", str(out)]) == 0
    assert "10 received copies of own frames left out" in capsys.readouterr().out
    got = list(can.ASCReader(str(out), relative_timestamp=False))
    assert len(got) == 20
    assert got[0].timestamp == pytest.approx(START_WALL_NS * 1e-9, abs=1e-3)
    assert [m.is_rx for m in got[:2]] == [True, False]
    assert "2026" in out.read_text().splitlines()[0]


def test_logconvert_turns_a_run_log_into_blf_on_the_wall_clock(tmp_path: Path) -> None:
    log = tmp_path / "run.mcap"
    _run_log_with_echoes(log)
    start_wall_ns = START_WALL_NS
    blf = tmp_path / "run.blf"
    subprocess.run([sys.executable, "-m", "can.logconvert", str(log), str(blf)], check=True, timeout=60)
    got = list(can.BLFReader(str(blf)))
    assert len(got) == 20  # the 10 echoes are left out
    assert got[0].timestamp == pytest.approx(start_wall_ns * 1e-9, abs=1e-3)
    assert sum(not m.is_rx for m in got) == 10 and all(m.arbitration_id != 0x201 or not m.is_rx for m in got)
    with_echoes = list(can.LogReader(str(log), keep_own_echoes=True))
    assert len(with_echoes) == 30


def test_player_sends_a_capture_onto_a_bus(tmp_path: Path) -> None:
    path = tmp_path / "capture.mcap"
    _capture(path, time.time())
    done = subprocess.run(
        [sys.executable, "-m", "can.player", "-i", "virtual", "-c", "dob-hil-player-test", str(path)],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr


def _netns_available() -> str | None:
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "unshare or ip is missing"
    probe = subprocess.run(["unshare", "-n", "true"], capture_output=True, check=False)
    return None if probe.returncode == 0 else f"cannot create a network namespace: {probe.stderr!r}"


DRIVER = """
import can, os, select, signal, subprocess, sys, time
# the logger stops on KeyboardInterrupt, which Python raises only if SIGINT was not ignored when it
# started: a shell's background job (CI scripts) ignores SIGINT, and children inherit that
signal.signal(signal.SIGINT, signal.SIG_DFL)
port, out = int(sys.argv[1]), sys.argv[2]
subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
subprocess.run(["ip", "route", "add", "224.0.0.0/4", "dev", "lo"], check=True)
logger = subprocess.Popen(
    [sys.executable, "-u", "-m", "can.logger", "-i", "udp_multicast", "-c", "239.74.163.9",
     "--bus-kwargs", f"port={port}", "-f", out],
    stdout=subprocess.PIPE,
)
rc = 1
try:
    assert logger.stdout is not None
    fd = logger.stdout.fileno()  # read raw: a buffered reader would hide lines from select
    deadline = time.monotonic() + 90.0
    seen = b""
    started = False
    while not started and time.monotonic() < deadline:  # the logger prints this once its bus is open
        ready, _, _ = select.select([fd], [], [], 1.0)
        if ready:
            chunk = os.read(fd, 4096)
            if not chunk:
                break  # the logger exited
            seen += chunk
            started = b"Can Logger" in seen
    if not started:
        sys.exit(f"the logger did not start within 90 s (exit status {logger.poll()}; it printed {seen!r})")
    bus = can.Bus(interface="udp_multicast", channel="239.74.163.9", port=port, receive_own_messages=False)
    for i in range(20):
        bus.send(can.Message(arbitration_id=0x300 + i, data=bytes([i] * 4), is_extended_id=False))
        time.sleep(0.01)
    time.sleep(3.0)  # the logger's recv(1) loop takes what is queued (it may be starved for a while)
    bus.shutdown()
finally:
    # never leave the logger running: it holds this process's stderr, which the test reads to EOF
    logger.send_signal(signal.SIGINT)
    try:
        rc = logger.wait(timeout=60)
    except subprocess.TimeoutExpired:
        logger.kill()
        logger.wait()
        print("the logger did not stop within 60 s of SIGINT; killed", file=sys.stderr)
sys.exit(rc)
"""


def test_python_can_logger_cli_records_a_bus_to_mcap(tmp_path: Path) -> None:
    """``python -m can.logger -f x.mcap`` on udp_multicast, inside a private network namespace
    with multicast routed to loopback and a private port: nothing leaves this machine."""
    reason = _netns_available()
    if reason:
        pytest.skip(reason)
    out = tmp_path / "bus.mcap"
    driver = tmp_path / "driver.py"
    driver.write_text(DRIVER)
    port = 47000 + (hash(str(tmp_path)) % 2000)
    done = subprocess.run(["unshare", "-n", sys.executable, str(driver), str(port), str(out)],
                          capture_output=True, text=True, timeout=240, check=False)  # fmt: skip
    assert done.returncode == 0 and out.exists(), done.stderr
    got = list(can.LogReader(str(out)))
    assert [m.arbitration_id for m in got] == [0x300 + i for i in range(20)], done.stderr
    assert all(bytes(m.data) == bytes([m.arbitration_id - 0x300] * 4) for m in got)


@pytest.mark.parametrize("layout", ["samples", "blocks"])
def test_a_cut_or_flipped_log_gives_frames_or_one_log_read_error(
    tmp_path: Path, run_writer: Any, layout: str
) -> None:
    """Whatever mcap's reader raises on a damaged file (its EndOfFile, RecordLengthLimitExceeded,
    a KeyError for a channel it never saw, ...) reaches the caller as LogReadError."""
    from dob_hil.errors import LogReadError

    src = tmp_path / "src.mcap"
    run_writer(src, 150, chunk_size_bytes=1024, compression="none", message_layout=layout)
    blob = src.read_bytes()
    rnd = random.Random(3)
    damaged = tmp_path / "damaged.mcap"
    outcomes = set()
    for i in range(120):
        if i % 2:
            data = bytearray(blob)
            data[rnd.randrange(len(data))] ^= 1 << rnd.randrange(8)
        else:
            data = bytearray(blob[: rnd.randrange(len(blob))])
        damaged.write_bytes(bytes(data))
        try:
            frames = list(can.LogReader(str(damaged)))
        except LogReadError:
            outcomes.add("error")
            continue
        outcomes.add("frames")
        assert len(frames) <= 300
    assert outcomes == {"error", "frames"}
