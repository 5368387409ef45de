"""``dob-hil run --live``: a real Foxglove WebSocket client connected during a run."""

from __future__ import annotations

import dataclasses
import json
import socket
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("foxglove", reason="the live extra (foxglove-sdk) is not installed")
pytest.importorskip("websockets", reason="the dev extra's websockets client is not installed")

from foxglove_ws_client import FoxgloveClient
from mcap_ros2._dynamic import generate_dynamic

from dob_hil.cli import main as cli_main
from dob_hil.config import Config, load_config
from dob_hil.live.packing import KIND_SAMPLE, Packer, unframe
from dob_hil.live.process import LiveError, LiveOptions
from dob_hil.live.tap import LiveTap, decimation_for
from dob_hil.log import read_log
from dob_hil.log.schemas import (
    CH_EVENT,
    CH_SAMPLE,
    CH_TRUTH,
    TOPIC_EVENT,
    TOPIC_SAMPLE,
    TOPIC_TRUTH,
    channel_specs,
    decode_event_cdr,
)
from dob_hil.loop.session import RunOptions, RunSummary, run_session
from dob_hil.scenarios import scenario_path

TOPICS = {TOPIC_SAMPLE, TOPIC_TRUTH, TOPIC_EVENT}
WAIT_S = 120.0  # generous: a loaded machine


@pytest.fixture
def paper_step() -> Config:
    return load_config(scenario_path("paper-step"))


def _patient(config: Config) -> Config:
    """Real time on a loaded machine: host timeout and watchdog wide enough never to trip."""
    drive = dataclasses.replace(config.drive, feedback_timeout_periods=100_000, watchdog_periods=100_000)
    return dataclasses.replace(config, drive=drive)


def test_decimation_is_the_rate_over_the_sample_rate() -> None:
    assert decimation_for(300_000, 100.0) == 33  # 3333 Hz -> every 33rd sample
    assert decimation_for(1_000_000, 100.0) == 10
    assert decimation_for(1_000_000, 5000.0) == 1  # never below every sample
    with pytest.raises(ValueError):
        decimation_for(1_000_000, 0.0)


def test_a_full_pipe_drops_and_counts_never_waits() -> None:
    import multiprocessing

    reader, writer = multiprocessing.Pipe(duplex=False)
    tap = LiveTap(writer.fileno(), 1)
    item = bytes(range(200))
    for _ in range(100_000):  # far more than any pipe holds: the writes past its capacity fail
        tap.put(item)
    assert tap.stats.forwarded > 0 and tap.stats.dropped > 0
    assert tap.stats.forwarded + tap.stats.dropped == 100_000
    for _ in range(tap.stats.forwarded):  # whatever went in is whole, message by message
        assert reader.recv_bytes() == item
    assert not reader.poll()
    writer.close()
    reader.close()


def test_a_client_connected_during_a_run_gets_decoded_samples_events_and_the_design(
    paper_step: Config, tmp_path: Path
) -> None:
    ready = threading.Event()
    where: list[tuple[str, int]] = []

    def on_ready(host: str, port: int) -> None:
        where.append((host, port))
        ready.set()

    log_path = tmp_path / "live.mcap"
    live = LiveOptions(port=0, rate_hz=100.0, linger_s=3.0, on_ready=on_ready)
    result: list[RunSummary | BaseException] = []

    def run() -> None:
        try:
            options = RunOptions(realtime=True, duration_s=4.0, log_path=log_path, live=live)
            result.append(run_session(_patient(paper_step), options))
        except BaseException as exc:  # handed to the test thread
            result.append(exc)
            ready.set()

    runner = threading.Thread(target=run, name="live-run")
    runner.start()
    try:
        assert ready.wait(WAIT_S), "the live server never reported ready"
        assert where, f"the run failed before serving: {result}"
        host, port = where[0]
        client = FoxgloveClient(f"ws://{host}:{port}")
        try:
            advertised = client.wait_for_topics(TOPICS, WAIT_S)
            client.subscribe(TOPICS)
            params = client.get_parameters(["dob_hil.design", "dob_hil.run.mode"], WAIT_S)
            while client.pump(5.0) and not any(
                m.topic == TOPIC_EVENT and b"run_end" in m.payload for m in client.messages
            ):
                pass
        finally:
            client.close()
    finally:
        runner.join(WAIT_S)
    assert not runner.is_alive()
    summary = result[0]
    assert isinstance(summary, RunSummary), summary
    assert summary.exit_reason == "completed"

    # the live channels are the log's: same topics, schema names, encodings and schema text
    specs = {
        s.topic: s
        for s in channel_specs(read_log(log_path).layout)
        if s.key in (CH_SAMPLE, CH_TRUTH, CH_EVENT)
    }
    for topic, spec in specs.items():
        ch = advertised[topic]
        assert ch["encoding"] == "cdr" and ch["schemaEncoding"] == "ros2msg"
        assert ch["schemaName"] == spec.schema_name
        assert ch["schema"] == spec.schema_data().decode()

    by_topic: dict[str, list[Any]] = {t: [] for t in TOPICS}
    for m in client.messages:
        by_topic[m.topic].append(m)
    assert len(by_topic[TOPIC_SAMPLE]) >= 5, f"{len(by_topic[TOPIC_SAMPLE])} samples arrived"
    assert len(by_topic[TOPIC_TRUTH]) >= 5

    # decoded with the advertised schema by an independent decoder (mcap_ros2), they are the
    # logged samples (the MCAP keeps every one; the live view every 33rd of them)
    ch = advertised[TOPIC_SAMPLE]
    decode = generate_dynamic(ch["schemaName"], ch["schema"])[ch["schemaName"]]
    data = read_log(log_path)
    logged = {int(s["seq"]): s for s in data.samples}
    seqs = []
    for m in by_topic[TOPIC_SAMPLE]:
        msg = decode(m.payload)
        row = logged[msg.seq]
        assert m.log_time_ns == msg.time_ns == int(row["time_ns"])
        np.testing.assert_array_equal(np.asarray(msg.x_ref), row["x_ref"])
        np.testing.assert_array_equal(np.asarray(msg.u_dist), row["u_dist"])
        np.testing.assert_array_equal(np.asarray(msg.u_applied_a), row["u_applied_a"])
        seqs.append(msg.seq)
    assert all(s % 33 == 0 for s in seqs) and seqs == sorted(seqs)
    truth_decode = generate_dynamic(advertised[TOPIC_TRUTH]["schemaName"], advertised[TOPIC_TRUTH]["schema"])
    t0 = truth_decode[advertised[TOPIC_TRUTH]["schemaName"]](by_topic[TOPIC_TRUTH][0].payload)
    assert len(t0.disturbance_a) == 1

    # events as they happen, after the samples they follow; run_end among them
    events = [decode_event_cdr(m.payload) for m in by_topic[TOPIC_EVENT]]
    assert any(e["kind"] == "run_end" for e in events)
    ev_decode = generate_dynamic(advertised[TOPIC_EVENT]["schemaName"], advertised[TOPIC_EVENT]["schema"])
    assert (
        ev_decode[advertised[TOPIC_EVENT]["schemaName"]](by_topic[TOPIC_EVENT][-1].payload).kind == "run_end"
    )

    # the design as a parameter: the log's design.json attachment
    values = {p["name"]: p.get("value") for p in params}
    assert json.loads(str(values["dob_hil.design"])) == json.loads(data.attachments["design.json"])
    assert values["dob_hil.run.mode"] == "realtime"
    assert summary.live is not None and summary.live["forwarded"] >= len(client.messages) - len(events)


def test_no_viewer_and_a_full_pipe_never_stop_the_run(paper_step: Config, tmp_path: Path) -> None:
    """Lockstep runs far faster than real time, every sample forwarded into the smallest pipe."""
    log_path = tmp_path / "nobody.mcap"
    live = LiveOptions(port=0, rate_hz=3333.0, pipe_bytes=4096, linger_s=0.0)
    summary = run_session(paper_step, RunOptions(log_path=log_path, live=live))
    assert summary.exit_reason == "completed"
    assert summary.live is not None and summary.live["forwarded"] >= 1
    data = read_log(log_path)
    assert len(data.samples) == summary.planned_samples  # the log keeps every sample
    stats = [e for e in data.events if e["kind"] == "live_stats"]
    assert len(stats) == 1
    assert stats[0]["data"] == {"forwarded": summary.live["forwarded"], "dropped": summary.live["dropped"]}
    assert (
        summary.live["forwarded"] + summary.live["dropped"] > summary.planned_samples
    )  # samples + truth + events


def test_packer_makes_the_logs_cdr(paper_step: Config, tmp_path: Path) -> None:
    log_path = tmp_path / "plain.mcap"
    run_session(paper_step, RunOptions(log_path=log_path, duration_s=0.01))
    from mcap.reader import make_reader

    with open(log_path, "rb") as f:
        first = next(m for _s, ch, m in make_reader(f).iter_messages() if ch.topic == TOPIC_SAMPLE)
    data = read_log(log_path)
    s = data.samples[0]
    args = tuple(
        tuple(v.tolist()) if isinstance(v, np.ndarray) else v.item()
        for v in (s[name] for name in s.dtype.names)
    )
    _t, payload = Packer(data.layout).pack(KIND_SAMPLE, args)
    assert payload == first.data
    kind, t, framed = unframe(Packer(data.layout).frame(KIND_SAMPLE, args))
    assert (kind, t, framed) == (KIND_SAMPLE, int(s["time_ns"]), first.data)
    with pytest.raises(ValueError):
        unframe(b"\x09" + bytes(8))


def test_cli_port_taken_is_one_line_and_exit_2(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        status = cli_main(
            ["run", "--scenario", "paper-step", "--no-log", "--no-progress", "--live", str(port)]
        )
    err = capsys.readouterr().err
    assert status == 2
    assert f"cannot serve on 127.0.0.1:{port}" in err and "Traceback" not in err


def test_bad_live_options_are_refused() -> None:
    with pytest.raises(LiveError, match="--live-rate"):
        LiveOptions(rate_hz=-1).check()
    with pytest.raises(LiveError, match="--live: port"):
        LiveOptions(port=70000).check()


def test_cli_live_announces_the_port_and_reports_in_the_summary(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["run", "--scenario", "paper-step", "--no-log", "--no-progress", "--json", "--live", "0"]
    status = cli_main([*argv, "--live-rate", "50"])
    out, err = capsys.readouterr()
    assert status == 0, err
    assert "dob-hil run: live view on ws://127.0.0.1:" in err
    live = json.loads(out)["live"]
    assert live["port"] > 0 and live["forwarded"] >= 1
