"""The block layout (``[run] log_layout = "blocks"``): the same records as the per-sample layout,
read back alike by every reader of dob_hil, in a smaller file; damage and windows as for the
per-sample layout. The mcap library's and the ros2 decoders' view is in
test_block_layout_independent.py."""

from __future__ import annotations

import json
import random
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dob_hil import cli
from dob_hil.errors import LogReadError
from dob_hil.log import LogData, LogWriter, read_log
from dob_hil.log.bench import PAPER_LAYOUT
from dob_hil.log.blocks import to_blocks
from dob_hil.log.check import check_sequences
from dob_hil.log.mcap_scan import scan, walk_chunk
from dob_hil.log.reader import iter_channel
from dob_hil.log.schemas import CDR_HEADER, MESSAGE_HEADER, OP_MESSAGE, TOPIC_SAMPLE, TOPIC_TRUTH
from dob_hil.log.stream import open_stream
from dob_hil.scenarios import scenario_path

N = 3000


def _fd_frames(tee: Any, k: int) -> None:
    if k % 97 == 5:  # some CAN FD frames and events among the periods
        tee.frame_raw(k * 300_000 + 7, 0x123, True, 15, bytes(range(k % 50, k % 50 + 24)), 1 << 3)
        tee.event(k * 300_000, "info", "note", f"period {k}", {"k": k})


@pytest.fixture(scope="module")
def both(
    tmp_path_factory: pytest.TempPathFactory, session_run_writer: Any
) -> dict[str, tuple[Path, LogData]]:
    """The same synthetic run in both layouts, in small chunks (many blocks)."""
    d = tmp_path_factory.mktemp("blocks")
    out = {}
    for layout in ("samples", "blocks"):
        path = d / f"{layout}.mcap"
        session_run_writer(path, N, extra=_fd_frames, chunk_size_bytes=16 * 1024, message_layout=layout)
        out[layout] = (path, read_log(path))
    return out


def _same(a: LogData, b: LogData) -> None:
    for name in ("samples", "frames", "fd_frames", "truth"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and len(x) == len(y), name
        assert x.tobytes() == y.tobytes(), name
    assert a.events == b.events


def test_a_block_log_reads_back_as_the_per_sample_log(both: dict[str, tuple[Path, LogData]]) -> None:
    (_, per_sample), (path, blocks) = both["samples"], both["blocks"]
    assert blocks.complete and blocks.warnings == []
    assert len(blocks.samples) == N and len(blocks.fd_frames) > 20 and len(blocks.events) > 20
    _same(per_sample, blocks)
    assert blocks.metadata["log_format"]["message_layout"] == "blocks"
    assert per_sample.metadata["log_format"]["message_layout"] == "samples"
    # one sample message per chunk (a run of records), not one per sample
    fmap = scan(path.read_bytes(), str(path))
    messages = sum(chunk.indexes.get(1, (0, 0))[1] for chunk in fmap.chunks)
    assert messages == sum(1 for chunk in fmap.chunks if 1 in chunk.indexes) < N / 10


def test_streamed_reads_and_counts_agree(both: dict[str, tuple[Path, LogData]]) -> None:
    (p_path, _), (b_path, blocks) = both["samples"], both["blocks"]
    parts = list(iter_channel(b_path, TOPIC_TRUTH, ["time_ns", "state"]))
    joined = np.concatenate(parts)
    assert np.array_equal(joined["state"], blocks.truth["state"])
    for path in (p_path, b_path):
        with open_stream(path, {TOPIC_SAMPLE: ("seq", "u_applied_a"), TOPIC_TRUTH: None}) as stream:
            assert stream.counts[TOPIC_SAMPLE] == N
            assert stream.counts[TOPIC_TRUTH] == len(blocks.truth)
            seq = np.concatenate([b.samples["seq"] for b in stream.blocks()])
        assert np.array_equal(seq, blocks.samples["seq"])


def test_sequences_are_complete_record_by_record(both: dict[str, tuple[Path, LogData]]) -> None:
    reports = {layout: check_sequences(path) for layout, (path, _) in both.items()}
    for topic, report in reports["blocks"].items():
        assert report.complete, report
        assert report.messages == reports["samples"][topic].messages  # records, not blocks


def test_a_block_log_is_much_smaller(tmp_path: Path, run_writer: Any) -> None:
    sizes = {}
    for layout in ("samples", "blocks"):
        path = tmp_path / f"{layout}.mcap"
        run_writer(path, 20_000, message_layout=layout)
        sizes[layout] = path.stat().st_size
    assert sizes["blocks"] < 0.75 * sizes["samples"], sizes


@pytest.mark.parametrize("seed", range(6))
def test_a_time_window_holds_every_sample_inside_it(both: dict[str, tuple[Path, LogData]], seed: int) -> None:
    rnd = random.Random(seed)
    t = both["samples"][1].samples["time_ns"]
    first = int(rnd.choice(t)) + rnd.randrange(-400_000, 400_000)
    last = first + rnd.randrange(0, 200_000_000)
    inside = {}
    for layout, (path, _) in both.items():
        got = read_log(path, log_time_window_ns=(first, last)).samples
        inside[layout] = got[(got["time_ns"] >= first) & (got["time_ns"] <= last)]
    want = t[(t >= first) & (t <= last)]
    assert np.array_equal(inside["blocks"]["time_ns"], want)
    assert inside["blocks"].tobytes() == inside["samples"].tobytes()


def test_a_cut_block_log_gives_the_prefix(both: dict[str, tuple[Path, LogData]], tmp_path: Path) -> None:
    path, whole = both["blocks"]
    blob = path.read_bytes()
    rnd = random.Random(7)
    recovered = []
    for cut in sorted(rnd.randrange(1, len(blob)) for _ in range(40)):
        cut_path = tmp_path / "cut.mcap"
        cut_path.write_bytes(blob[:cut])
        try:
            data = read_log(cut_path)
        except LogReadError:
            continue
        assert data.warnings and not data.complete
        n = len(data.samples)
        assert data.samples.tobytes() == whole.samples[:n].tobytes()
        assert data.truth.tobytes() == whole.truth[: len(data.truth)].tobytes()
        with open_stream(cut_path, {TOPIC_SAMPLE: ("seq",)}, events=False) as stream:
            assert stream.counts[TOPIC_SAMPLE] == n  # counted block by block without the summary
        recovered.append(n)
    assert recovered == sorted(recovered) and recovered[-1] > N // 2


def test_flipped_bytes_give_rows_of_the_log_or_a_warning(
    both: dict[str, tuple[Path, LogData]], tmp_path: Path
) -> None:
    path, whole = both["blocks"]
    blob = bytearray(path.read_bytes())
    rnd = random.Random(11)
    index = {int(s): i for i, s in enumerate(whole.samples["seq"])}
    for _ in range(40):
        damaged = bytearray(blob)
        at = rnd.randrange(len(blob))
        damaged[at] ^= 1 << rnd.randrange(8)
        p = tmp_path / "flip.mcap"
        p.write_bytes(bytes(damaged))
        try:
            data = read_log(p)
        except LogReadError:
            continue
        if data.samples.tobytes() != whole.samples.tobytes():
            assert data.warnings, f"byte {at}: samples changed without a warning"
            rows = [index.get(int(s), -1) for s in data.samples["seq"]]
            assert -1 not in rows and data.samples.tobytes() == whole.samples[rows].tobytes()


def test_a_block_whose_count_lies_is_skipped_with_a_warning(tmp_path: Path, run_writer: Any) -> None:
    path = tmp_path / "lie.mcap"
    run_writer(path, 200, message_layout="blocks", compression="none", chunk_interval_ns=10**12)
    blob = bytearray(path.read_bytes())
    whole = read_log(path)
    # the first sample block: its CDR header is followed by the count (uncompressed chunks)
    seq0 = MESSAGE_HEADER.size  # a message record's header, then the CDR header, then the count
    at = blob.find(b"\x05", 0)
    while True:  # find a Message record of channel 1 (samples) with sequence 0 and a CDR header
        at = blob.find(bytes([OP_MESSAGE]), at + 1)
        assert at > 0
        _op, _length, channel, seq, _t, _p = MESSAGE_HEADER.unpack_from(blob, at)
        if channel == 1 and seq == 0 and blob[at + seq0 : at + seq0 + 4] == CDR_HEADER:
            break
    count_at = at + seq0 + 4
    (count,) = struct.unpack_from("<I", blob, count_at)
    assert count == len(whole.samples)
    struct.pack_into("<I", blob, count_at, count + 1)
    p = tmp_path / "lied.mcap"
    p.write_bytes(bytes(blob))
    data = read_log(p, verify_crc=False)  # the chunk's CRC would reject the whole chunk
    assert len(data.samples) == 0 and any("blocks of the wrong length" in w for w in data.warnings)
    assert data.truth.tobytes() == whole.truth.tobytes()


def _record(channel: int, seq: int, t: int, body: bytes) -> bytes:
    return MESSAGE_HEADER.pack(OP_MESSAGE, 22 + 4 + len(body), channel, seq, t, t) + CDR_HEADER + body


def test_to_blocks_splits_at_gaps_and_going_back_in_time_and_keeps_every_record() -> None:
    body = struct.Struct("<QI")  # a record of 12 bytes: time, value (stride 16)
    records = [
        _record(1, 0, 10, body.pack(10, 0)),
        _record(5, 0, 11, b"event"),
        _record(1, 1, 20, body.pack(20, 1)),
        _record(1, 3, 30, body.pack(30, 3)),  # a gap: a new block
        _record(1, 4, 25, body.pack(25, 4)),  # back in time: a new block
        _record(1, 5, 40, body.pack(40, 5)),
    ]
    offsets = np.cumsum([0] + [len(r) for r in records[:-1]]).astype(np.int64)
    data, out_offsets, counts = to_blocks(b"".join(records), offsets, {1: (12, 16)})
    assert counts == {1: 5}
    walk = walk_chunk(data)
    assert walk.offsets == out_offsets and not walk.problem
    heads = [MESSAGE_HEADER.unpack_from(data, o) for o in walk.offsets]
    assert [(h[2], h[3], h[4], h[5]) for h in heads] == [
        (1, 0, 10, 20),
        (5, 0, 11, 11),
        (1, 3, 30, 30),
        (1, 4, 25, 40),
    ]
    values = []
    for o, h in zip(walk.offsets, heads, strict=True):
        if h[2] != 1:
            assert data[o + 35 : o + 9 + h[1]] == b"event"
            continue
        (n,) = struct.unpack_from("<I", data, o + 35)
        values += [body.unpack_from(data, o + 43 + 16 * j)[1] for j in range(n)]
    assert values == [0, 1, 3, 4, 5]
    with pytest.raises(ValueError, match="another length"):
        to_blocks(b"".join(records), offsets, {1: (13, 16)})


def test_run_analyze_and_verify_a_block_log(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    logs = {}
    for layout in ("samples", "blocks"):
        logs[layout] = tmp_path / f"{layout}.mcap"
        argv = ["run", "paper-step", "--duration", "0.3", "--log", str(logs[layout]), "--no-progress"]
        assert cli.main([*argv, "--log-layout", layout, "--json"]) == 0
    capsys.readouterr()
    results = {}
    for layout, path in logs.items():
        assert cli.main(["analyze", str(path), "--json", "--no-plots"]) == 0
        results[layout] = json.loads(capsys.readouterr().out)
        assert cli.main(["replay", str(path), "--verify"]) == 0
        capsys.readouterr()
    a, b = results["samples"], results["blocks"]
    a, b = (r[0] if isinstance(r, list) else r for r in (a, b))
    assert b["complete"] is True
    for key in ("samples", "tracking_rms", "max_abs_current_A"):
        if key in a:
            assert a[key] == b[key], key


def test_a_bad_log_layout_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = scenario_path("paper-step").read_text().replace("[run]\n", '[run]\nlog_layout = "rows"\n', 1)
    config = tmp_path / "bad.toml"
    config.write_text(text)
    assert cli.main(["run", str(config), "--duration", "0.01", "--no-log", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "run.log_layout" in err[0] and "rows" in err[0]
    with pytest.raises(SystemExit) as exc:
        cli.main(["run", "paper-step", "--log-layout", "rows"])
    assert exc.value.code == 2


def test_a_huge_count_in_a_cut_log_is_a_warning_not_an_allocation(tmp_path: Path, run_writer: Any) -> None:
    """A block claiming 2**32 - 1 records in a log without its summary: the counting pass and the
    readers take it for damage (its length does not fit), and nothing near 2**32 is allocated."""
    path = tmp_path / "huge.mcap"
    run_writer(path, 300, message_layout="blocks", compression="none", chunk_interval_ns=10**12)
    blob = bytearray(path.read_bytes())
    whole = read_log(path)
    at = 0
    while True:
        at = blob.find(bytes([OP_MESSAGE]), at + 1)
        assert at > 0
        _op, _length, channel, seq, _t, _p = MESSAGE_HEADER.unpack_from(blob, at)
        if channel == 1 and seq == 0 and blob[at + 31 : at + 35] == CDR_HEADER:
            break
    struct.pack_into("<I", blob, at + 35, 0xFFFFFFFF)
    cut = tmp_path / "huge-cut.mcap"
    cut.write_bytes(bytes(blob[: blob.rfind(b"\x0f")]))  # no DataEnd, no summary: counted block by block
    data = read_log(cut, verify_crc=False)
    assert len(data.samples) == 0 and not data.complete
    assert any("blocks of the wrong length" in w for w in data.warnings)
    assert data.truth.tobytes() == whole.truth[: len(data.truth)].tobytes()
    with open_stream(cut, {TOPIC_SAMPLE: ("seq",)}, events=False) as stream:
        assert stream.counts[TOPIC_SAMPLE] == 0  # the chunk's CRC fails here: nothing counted
    report = check_sequences(cut)
    assert report[TOPIC_SAMPLE].messages == 0


@pytest.mark.parametrize("layout", ["samples", "blocks"])
def test_a_window_finds_a_record_whose_chunk_ends_after_the_next_begins(tmp_path: Path, layout: str) -> None:
    """A late frame opens a chunk earlier than the previous chunk's last record: the read by time
    still takes that chunk (a block chunk declares its last record's time as its end)."""
    path = tmp_path / f"late-{layout}.mcap"
    with LogWriter(path, PAPER_LAYOUT, message_layout=layout, chunk_size_bytes=1024) as log:
        times = [i * 1000 for i in range(40)]
        times.insert(30, 500)  # after the first chunk closed
        for t in times:
            log.frame_raw(t, 0x181, True, 2, b"ab", 0)
    for first in range(0, 40_000, 1000):
        got = read_log(path, log_time_window_ns=(first, first)).frames["timestamp_ns"]
        assert (got == first).sum() == 1, first


def test_a_block_too_short_for_its_count_is_lost_to_check_sequences_without_a_traceback(
    tmp_path: Path, run_writer: Any
) -> None:
    path = tmp_path / "short.mcap"
    run_writer(path, 50, message_layout="blocks", compression="none", chunk_interval_ns=10**12)
    blob = bytearray(path.read_bytes())
    at = 0
    while True:  # the sample block: shorten its record to its header and CDR header
        at = blob.find(bytes([OP_MESSAGE]), at + 1)
        _op, length, channel, seq, _t, _p = MESSAGE_HEADER.unpack_from(blob, at)
        if channel == 1 and seq == 0 and blob[at + 31 : at + 35] == CDR_HEADER:
            break
    cut = blob[: at + 35] + blob[at + 9 + length :]  # no count, no records
    struct.pack_into("<Q", cut, at + 1, 22 + 4)
    p = tmp_path / "short-cut.mcap"
    p.write_bytes(bytes(cut[: cut.rfind(b"\x0f")]))  # the chunk no longer fits its index: no summary either
    report = check_sequences(p)  # the chunk is re-walked or skipped: never an IndexError
    assert report[TOPIC_SAMPLE].messages == 0
    data = read_log(p, verify_crc=False)
    assert len(data.samples) == 0 and data.warnings


def test_a_block_log_without_schemas_reads_through_its_log_format(tmp_path: Path, run_writer: Any) -> None:
    path = tmp_path / "noschema.mcap"
    run_writer(path, 500, message_layout="blocks")
    whole = read_log(path)
    blob = bytearray(path.read_bytes())
    pos = 8
    while pos < len(blob) - 8:  # hide every Schema and Channel record (opcode 0x80: unknown, skipped)
        op, length = blob[pos], struct.unpack_from("<Q", blob, pos + 1)[0]
        if op == 0x02:
            break
        if op in (0x03, 0x04):
            blob[pos] = 0x80
        pos += 9 + length
    p = tmp_path / "hidden.mcap"
    p.write_bytes(bytes(blob))
    data = read_log(p)
    assert any("channel schemas not found" in w for w in data.warnings)
    _same(whole, data)


def test_a_summary_claiming_more_records_than_the_chunks_hold_is_capped(tmp_path: Path) -> None:
    """A crafted, closed block log: its summary claims 10**12 samples and its one chunk 2**50
    bytes; the reader counts no more than the chunks it would decompress can hold (none here)."""
    from mcap.writer import CompressionType, Writer

    from dob_hil.log.metadata import log_format_metadata
    from dob_hil.log.schemas import channel_specs

    path = tmp_path / "crafted.mcap"
    with path.open("wb") as f:
        w = Writer(f, compression=CompressionType.NONE)
        w.start("x", "dob_hil")
        ids = {}
        for spec in channel_specs(PAPER_LAYOUT, "blocks"):
            sid = w.register_schema(spec.schema_name, spec.schema_encoding, spec.schema_data())
            ids[spec.key] = w.register_channel(spec.topic, spec.message_encoding, sid)
        w.add_metadata("log_format", log_format_metadata(PAPER_LAYOUT, "blocks"))
        w.add_metadata("summary", {"samples_written": str(10**12)})
        empty_block = CDR_HEADER + struct.pack("<II", 0, 0)
        w.add_message(ids[1], log_time=1, data=empty_block, publish_time=1, sequence=0)
        w.finish()
    blob = bytearray(path.read_bytes())
    pos = 8
    while blob[pos] != 0x06:  # the chunk record: its uncompressed size, after its two times
        pos += 9 + struct.unpack_from("<Q", blob, pos + 1)[0]
    struct.pack_into("<Q", blob, pos + 9 + 16, 2**50)
    path.write_bytes(bytes(blob))
    data = read_log(path)
    assert len(data.samples) == 0 and any("implausible uncompressed size" in w for w in data.warnings)
    with open_stream(path, {TOPIC_SAMPLE: None}) as stream:
        assert stream.counts[TOPIC_SAMPLE] == 0
