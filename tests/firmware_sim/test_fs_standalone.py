"""``python -m firmware_sim`` as its own process: a real exchange over udp_multicast (and SocketCAN
where it exists), clean stop on SIGINT, exit status 2 for a bad config."""

from __future__ import annotations

import contextlib
import os
import random
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
from fs_support import REPO_ROOT, Host, dump_toml, feedbacks, merged_data, toml_text
from udp_isolation import private_udp_channel

from dob_hil.link.protocol import ControlRequest, DriveState, FeedbackFrame, HeartbeatFrame, Status
from firmware_sim.cli import parse_args
from firmware_sim.truth import decode_truth

pytestmark = pytest.mark.realtime


def _env() -> dict[str, str]:
    # the checkout first, so the process runs this firmware_sim whatever is installed
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


def _run(args: list[str], cwd: Path, timeout_s: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "firmware_sim", *args],
        check=False,
        cwd=cwd,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )


def _open_bus(interface: str, channel: str) -> can.BusABC:
    try:
        return can.Bus(interface=interface, channel=channel)
    except (OSError, can.CanError, ImportError, NotImplementedError, ValueError) as exc:
        pytest.skip(f"{interface} bus {channel!r} cannot be opened here: {exc}")


@pytest.fixture(params=["udp_multicast", "socketcan"])
def bus_spec(request: pytest.FixtureRequest) -> Iterator[tuple[str, str, can.BusABC]]:
    with contextlib.ExitStack() as stack:
        if request.param == "udp_multicast":  # a private port in this worker's network namespace
            channel = stack.enter_context(private_udp_channel()).channel
        else:
            channel = "vcan0"
        bus = _open_bus(request.param, channel)
        try:
            yield request.param, channel, bus
        finally:
            bus.shutdown()


def test_exchange_with_a_standalone_drive(bus_spec: tuple[str, str, can.BusABC], tmp_path: Path) -> None:
    interface, channel, bus = bus_spec
    node_id = random.randint(2, 15)  # other tests on the same multicast port: filter by id
    cfg = tmp_path / "drive.toml"
    cfg.write_text(
        # a 60 s watchdog: a starved machine must not trip it between two answers
        toml_text(plant={"period_us": 1000.0}, drive={"node_id": node_id, "watchdog_periods": 60_000})
    )
    truth_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    truth_sock.bind(("127.0.0.1", 0))
    truth_sock.settimeout(10.0)
    port = truth_sock.getsockname()[1]
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "firmware_sim",
            str(cfg),
            "-i",
            interface,
            "-c",
            channel,
            "--truth-port",
            str(port),
            "--spin-us",
            "0",
            "--duration",
            "60",
        ],
        cwd=tmp_path,
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        host = Host(bus, node_id)
        host.wait_for(FeedbackFrame, timeout_s=30.0)  # the process is up and streaming
        host.control(ControlRequest.ENABLE)
        # a periodic heartbeat sent before the drive read the enable may still say DISABLED
        deadline = time.monotonic() + 30.0
        frames = host.wait_for(HeartbeatFrame, timeout_s=30.0)
        while frames[-1] != HeartbeatFrame(DriveState.ENABLED) and time.monotonic() < deadline:
            frames = host.wait_for(HeartbeatFrame, timeout_s=30.0)
        assert frames[-1] == HeartbeatFrame(DriveState.ENABLED)
        answered = 0
        deadline = time.monotonic() + 60.0  # a bound against a hang only
        while answered < 20 and time.monotonic() < deadline:
            fb = host.wait_for(FeedbackFrame)[-1]
            assert isinstance(fb, FeedbackFrame)
            if fb.status & Status.ENABLED:
                host.command(400, fb.seq)
                answered += 1
        assert answered == 20
        late = feedbacks(host.wait_for(FeedbackFrame))
        assert late[-1].status & Status.ENABLED and not late[-1].status & Status.FAULT
        truth = [decode_truth(truth_sock.recv(4096)) for _ in range(5)]
        assert [t.period_index for t in truth] == sorted(t.period_index for t in truth)
        assert len(truth[0].state) == 2
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            _, err = proc.communicate(timeout=15.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
        truth_sock.close()
    assert proc.returncode == 0, err
    assert "stopped after" in err
    assert "Traceback" not in err


def test_sigterm_and_duration_stop_cleanly(tmp_path: Path) -> None:
    cfg = tmp_path / "drive.toml"
    cfg.write_text(toml_text(plant={"period_us": 1000.0}))
    channel = f"firmware-sim-standalone-{os.getpid()}"
    done = _run([str(cfg), "-i", "virtual", "-c", channel, "--duration", "0.3"], tmp_path)
    assert done.returncode == 0, done.stderr
    assert "stopped after" in done.stderr
    proc = subprocess.Popen(
        [sys.executable, "-m", "firmware_sim", str(cfg), "-i", "virtual", "-c", channel],
        cwd=tmp_path,
        env=_env(),
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stderr is not None
    assert "node 1" in proc.stderr.readline()  # started
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=15.0)
    assert proc.returncode == 0 and "stopped after" in err


@pytest.mark.parametrize(
    ("plant", "field"),
    [
        ({"A": [[0.0, 1.0, 2.0], [0.0, -128.59, 0.0]]}, "plant.A: must be square"),
        (  # two inputs, one output: not square, so no axis per input and output
            {"B": [[0.0, 0.0], [1.0, 1.0]], "input_names": ["a", "b"]},
            "plant.C: a drive runs one axis per input and output",
        ),
    ],
)
def test_bad_config_exits_2_with_one_line(plant: dict[str, object], field: str, tmp_path: Path) -> None:
    cfg = tmp_path / "bad.toml"
    cfg.write_text(dump_toml(merged_data(plant=plant, design={"estimator": {}, "feedback": {}, "dob": {}})))
    done = _run([str(cfg), "-i", "virtual", "-c", "unused"], tmp_path)
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and field in done.stderr, done.stderr


def test_a_node_id_beyond_the_protocol_exits_2_with_one_line(tmp_path: Path) -> None:
    cfg = tmp_path / "bad.toml"
    cfg.write_text(dump_toml(merged_data(drive={"node_id": 99})))
    done = _run([str(cfg), "-i", "virtual", "-c", "unused"], tmp_path)
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and "drive.node_id" in done.stderr and "0..15" in done.stderr, (
        done.stderr
    )


def test_missing_config_file_exits_2(tmp_path: Path) -> None:
    done = _run([str(tmp_path / "nope.toml")], tmp_path)
    assert done.returncode == 2
    assert done.stderr.strip() == f"firmware_sim: error: {tmp_path / 'nope.toml'}: no such file"


def test_argument_parsing() -> None:
    args = parse_args(
        ["c.toml", "-i", "udp_multicast", "-c", "239.74.163.2", "-b", "500000", "--truth-port", "9000"]
    )
    assert (args.config, args.interface, args.channel, args.bitrate, args.truth_port) == (
        "c.toml",
        "udp_multicast",
        "239.74.163.2",
        500000,
        9000,
    )
    assert args.duration is None and args.spin_us == "auto" and args.variant == "reference"
    assert parse_args(["c.toml", "--spin-us", "25"]).spin_us == 25.0
    for bad in (["--spin-us", "fast"], ["--spin-us", "-1"], ["--watchdog-periods", "0"]):
        with pytest.raises(SystemExit):
            parse_args(["c.toml", *bad])
    with pytest.raises(SystemExit) as info:
        parse_args(["c.toml", "--duration", "-1"])
    assert info.value.code == 2
