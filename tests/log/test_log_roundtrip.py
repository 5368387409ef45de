"""Write a run, read every channel back with mcap + mcap_ros2 + json, and with read_log."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import can
import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from dob_hil.log import LogLayout, LogWriter, read_log
from dob_hil.log.schemas import (
    CAN_FLAG_ERROR,
    CAN_FLAG_EXTENDED,
    CAN_FLAG_FD,
    CAN_FLAG_REMOTE,
    sample_fields,
    truth_fields,
)

SAMPLE_NAMES = [f.name for f in sample_fields(LogLayout(1, 1, 1, 1))]
TRUTH_NAMES = [f.name for f in truth_fields(LogLayout(1, 1, 1, 1))]
FRAME_NAMES = ["timestamp_ns", "arbitration_id", "direction", "dlc", "flags", "data"]


def _as_list(value: Any) -> Any:
    """mcap_ros2 gives uint8 arrays as bytes, other arrays as lists."""
    return list(value) if isinstance(value, bytes | bytearray | list | tuple) else value


def _frame_row(args: tuple[Any, ...]) -> tuple[Any, ...]:
    timestamp_ns, arbitration_id, is_rx, dlc, data, flags = args
    return (timestamp_ns, arbitration_id, 0 if is_rx else 1, dlc, flags, list(data) + [0] * (8 - len(data)))


def _library_messages(path: Path) -> dict[str, list[Any]]:
    out: dict[str, list[Any]] = {}
    with path.open("rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
        for _schema, channel, message in reader.iter_messages():
            out.setdefault(channel.topic, []).append(message)
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        decoded: dict[str, list[Any]] = {}
        # one decoder factory decodes every channel, the events too (all ros2msg/cdr)
        for _schema, channel, message, obj in reader.iter_decoded_messages():
            decoded.setdefault(channel.topic, []).append((message.log_time, obj))
    assert len(decoded.get("/dob_hil/event", [])) == len(out.get("/dob_hil/event", []))
    events = [
        {"time_ns": obj.time_ns, "level": obj.level, "kind": obj.kind, "message": obj.message,
         "data": json.loads(obj.data)}
        for _, obj in decoded.pop("/dob_hil/event", [])
    ]  # fmt: skip
    return {**decoded, "/dob_hil/event": events}


def test_every_channel_matches_what_was_written(small_log: tuple[Path, Any, LogWriter]) -> None:
    path, rec, _ = small_log
    lib = _library_messages(path)
    data = read_log(path)
    assert data.warnings == [] and data.complete

    assert len(lib["/dob_hil/sample"]) == len(rec.samples) == len(data.samples) == 2000
    for (log_time, msg), args, row in zip(lib["/dob_hil/sample"], rec.samples, data.samples, strict=True):
        assert log_time == args[0]
        for name, value in zip(SAMPLE_NAMES, args, strict=True):
            assert _as_list(getattr(msg, name)) == _as_list(
                list(value) if isinstance(value, list | tuple) else value
            )
            ours = row[name]
            assert (ours.tolist() if isinstance(ours, np.ndarray) else ours) == getattr(msg, name)

    assert len(lib["/dob_hil/can"]) == len(rec.frames) == len(data.frames) == 4000
    for (log_time, msg), args, row in zip(lib["/dob_hil/can"], rec.frames, data.frames, strict=True):
        expected = _frame_row(args)
        assert log_time == args[0]
        assert tuple(_as_list(getattr(msg, n)) for n in FRAME_NAMES) == expected
        assert (*(int(row[n]) for n in FRAME_NAMES[:-1]), row["data"].tolist()) == expected

    assert len(lib["/dob_hil/truth"]) == len(rec.truth_rows) == len(data.truth) == 2000
    for (_, msg), args, row in zip(lib["/dob_hil/truth"], rec.truth_rows, data.truth, strict=True):
        for name, value in zip(TRUTH_NAMES, args, strict=True):
            expected_value = list(value) if isinstance(value, list | tuple) else value
            assert getattr(msg, name) == expected_value
            ours = row[name]
            assert (ours.tolist() if isinstance(ours, np.ndarray) else ours) == expected_value

    assert lib["/dob_hil/event"] == rec.events == data.events
    assert len(data.fd_frames) == 0


def test_metadata_attachments_and_summary(small_log: tuple[Path, Any, LogWriter]) -> None:
    path, _, log = small_log
    data = read_log(path)
    with path.open("rb") as f:
        reader = make_reader(f)
        lib_meta = {m.name: m.metadata for m in reader.iter_metadata()}
        lib_attachments = {a.name: a.data for a in reader.iter_attachments()}
    assert lib_meta == data.metadata
    assert lib_attachments == data.attachments
    assert data.attachments["design.json"] == b'{"Kc": [[1.0, 2.0]]}'
    assert data.attachments["config.toml"].decode() == "[plant]\nname = 'ü'\n"
    assert set(data.metadata) == {"log_format", "versions", "run", "summary"}
    assert data.metadata["run"]["period_ns"] == "300000"
    assert {"numpy", "python-can", "mcap", "python", "dob_hil", "platform"} <= set(data.metadata["versions"])
    summary = data.metadata["summary"]
    assert summary["exit_reason"] == "closed"
    assert summary["samples_written"] == "2000" and summary["frames_written"] == "4000"
    assert summary["events_written"] == str(len(data.events))
    assert summary["dropped_records"] == "0"
    assert data.layout == LogLayout(2, 1, 1, 2)
    stats = log.stats
    assert stats.dropped_records == 0
    assert stats.written_records is not None and stats.written_records["samples_written"] == 2000
    assert stats.enqueued_records == 2000 * 4 + len(data.events)


def test_other_dimensions(tmp_path: Path, run_writer: Any) -> None:
    layout = LogLayout(n_states=5, n_inputs=2, n_outputs=3, n_plant_states=4)
    rec, _ = run_writer(tmp_path / "dims.mcap", 300, layout)
    data = read_log(tmp_path / "dims.mcap")
    assert data.layout == layout and data.warnings == []
    assert data.samples.dtype["x_hat"].shape == (5,) and data.samples.dtype["dac_counts"].shape == (2,)
    assert data.samples["counts"].shape == (300, 3)
    for args, row in zip(rec.samples, data.samples, strict=True):
        for name, value in zip(SAMPLE_NAMES, args, strict=True):
            ours = row[name]
            assert (ours.tolist() if isinstance(ours, np.ndarray) else ours) == (
                list(value) if isinstance(value, list | tuple) else value
            )
    assert np.array_equal(data.truth["state"], np.array([r[1] for r in rec.truth_rows]))


def test_can_messages_classic_fd_error_remote(tmp_path: Path) -> None:
    msgs = [
        (can.Message(timestamp=1.5, arbitration_id=0x181, is_extended_id=False, data=b"\x01\x02"), True),
        (can.Message(timestamp=1.6, arbitration_id=0x1ABCDEF, is_extended_id=True, data=bytes(8)), False),
        (
            can.Message(
                timestamp=1.7, arbitration_id=0x7FF, is_extended_id=False, is_remote_frame=True, dlc=4
            ),
            True,
        ),
        (can.Message(timestamp=1.8, is_error_frame=True, is_extended_id=False, data=b"\x20"), True),
        (
            can.Message(
                timestamp=1.9, arbitration_id=0x10, is_extended_id=False, is_fd=True, data=bytes(range(12))
            ),
            True,
        ),
        (
            can.Message(
                timestamp=2.0, arbitration_id=0x11, is_extended_id=False, is_fd=True, data=bytes(range(64))
            ),
            False,
        ),
        (
            can.Message(timestamp=2.1, arbitration_id=0x12, is_extended_id=False, is_fd=True, data=b"\xff"),
            True,
        ),
    ]
    path = tmp_path / "can.mcap"
    with LogWriter(path, LogLayout(2, 1, 1, 2)) as log:
        for msg, is_rx in msgs:
            log.frame(msg, is_rx)
    data = read_log(path)
    classic, fd = data.frames, data.fd_frames
    assert classic["timestamp_ns"].tolist() == [
        1_500_000_000,
        1_600_000_000,
        1_700_000_000,
        1_800_000_000,
        2_100_000_000,
    ]
    assert classic["flags"].tolist() == [0, CAN_FLAG_EXTENDED, CAN_FLAG_REMOTE, CAN_FLAG_ERROR, CAN_FLAG_FD]
    assert classic["direction"].tolist() == [0, 1, 0, 0, 0]
    assert classic["dlc"].tolist() == [2, 8, 4, 1, 1]
    assert classic["data"][0].tolist() == [1, 2, 0, 0, 0, 0, 0, 0]
    assert classic["arbitration_id"][1] == 0x1ABCDEF
    assert fd["arbitration_id"].tolist() == [0x10, 0x11]
    assert fd["dlc"].tolist() == [12, 64]
    assert fd["data"][0].tolist() == list(range(12)) + [0] * 52
    assert fd["data"][1].tolist() == list(range(64))
    assert (fd["flags"] & CAN_FLAG_FD).all()
    with path.open("rb") as f:  # and the library agrees on the FD channel
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        lib = [obj for _, _, _, obj in reader.iter_decoded_messages(topics=["/dob_hil/can_fd"])]
    assert [list(m.data) for m in lib] == fd["data"].tolist()


def test_a_subset_of_fields_reads_the_same_values(small_log: tuple[Path, Any, Any]) -> None:
    path = small_log[0]
    whole = read_log(path)
    keep = {"/dob_hil/sample": ["time_ns", "x_hat", "flags"], "/dob_hil/can": ["timestamp_ns", "dlc"]}
    part = read_log(path, fields=keep)
    assert part.samples.dtype.names == ("time_ns", "x_hat", "flags")
    assert part.frames.dtype.names == ("timestamp_ns", "dlc")
    for name in keep["/dob_hil/sample"]:
        np.testing.assert_array_equal(part.samples[name], whole.samples[name])
    for name in keep["/dob_hil/can"]:
        np.testing.assert_array_equal(part.frames[name], whole.frames[name])
    assert part.samples.dtype.itemsize < whole.samples.dtype.itemsize
    np.testing.assert_array_equal(part.truth, whole.truth)  # topics not named are read whole


def test_an_unknown_field_is_named(small_log: tuple[Path, Any, Any]) -> None:
    import pytest

    from dob_hil.errors import LogReadError

    with pytest.raises(LogReadError, match="no field 'x_nope'"):
        read_log(small_log[0], fields={"/dob_hil/sample": ["x_nope"]})
