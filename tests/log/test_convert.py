"""``dob-hil export --format mcap --log-layout``: a log rewritten in the other message layout keeps
every record, its sequence number, the metadata and the attachments."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from dob_hil import cli
from dob_hil.log import LogData, read_log
from dob_hil.log.check import check_sequences
from dob_hil.log.convert import convert_layout
from dob_hil.log.digest import log_digest


def _fd_and_events(tee: Any, k: int) -> None:
    if k % 61 == 3:
        tee.frame_raw(k * 300_000 + 9, 0x321, False, 13, bytes(range(k % 40, k % 40 + 20)), 1 << 3)
        tee.event(k * 300_000, "warning", "note", f"period {k}", {"k": k})


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory, session_run_writer: Any) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("convert")
    out = {}
    for layout in ("samples", "blocks"):
        out[layout] = d / f"{layout}.mcap"
        options = {"chunk_size_bytes": 8192, "message_layout": layout}
        session_run_writer(out[layout], 2500, extra=_fd_and_events, **options)
    return out


def _same_records(a: LogData, b: LogData) -> None:
    for name in ("samples", "frames", "fd_frames", "truth"):
        assert getattr(a, name).tobytes() == getattr(b, name).tobytes(), name
    assert a.events == b.events


@pytest.mark.parametrize("source", ["samples", "blocks"])
@pytest.mark.parametrize("target", ["samples", "blocks"])
def test_a_converted_log_has_every_record_in_the_target_layout(
    logs: dict[str, Path], tmp_path: Path, source: str, target: str
) -> None:
    out = tmp_path / f"{source}-to-{target}.mcap"
    result = convert_layout(logs[source], out, target)
    original, converted = read_log(logs[source]), read_log(out)
    assert result.warnings == [] and converted.complete and converted.warnings == []
    _same_records(original, converted)
    assert result.records == len(original.samples) + len(original.frames) + len(original.fd_frames) + len(
        original.truth
    ) + len(original.events)
    assert converted.metadata["log_format"]["message_layout"] == target
    assert {k: v for k, v in converted.metadata.items() if k != "log_format"} == {
        k: v for k, v in original.metadata.items() if k != "log_format"
    }
    assert converted.attachments == original.attachments
    before, after = check_sequences(logs[source]), check_sequences(out)
    assert {t: (s.messages, s.missing, s.duplicates) for t, s in after.items()} == {
        t: (s.messages, s.missing, s.duplicates) for t, s in before.items()
    }
    assert all(s.complete for s in after.values())
    assert log_digest(out) == log_digest(logs[source])


def test_blocks_to_samples_and_back_sizes(logs: dict[str, Path], tmp_path: Path) -> None:
    samples = tmp_path / "s.mcap"
    convert_layout(logs["blocks"], samples, "samples")
    blocks = tmp_path / "b.mcap"
    convert_layout(samples, blocks, "blocks")
    assert blocks.stat().st_size < 0.8 * samples.stat().st_size
    _same_records(read_log(logs["blocks"]), read_log(blocks))


def test_a_cut_log_converts_as_far_as_it_reads(logs: dict[str, Path], tmp_path: Path) -> None:
    blob = logs["blocks"].read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(blob[: len(blob) * 2 // 3])
    out = tmp_path / "cut-samples.mcap"
    result = convert_layout(cut, out, "samples")
    assert result.warnings
    partial, converted = read_log(cut), read_log(out)
    _same_records(partial, converted)
    assert converted.complete and 0 < len(converted.samples) < 2500


def test_the_command_line(logs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "via-cli.mcap"
    argv = ["export", str(logs["blocks"]), "--format", "mcap", "--log-layout", "samples", "--out", str(out)]
    assert cli.main(argv) == 0
    assert "samples layout" in capsys.readouterr().out
    _same_records(read_log(logs["blocks"]), read_log(out))
    assert cli.main(["analyze", str(out), "--json", "--no-plots"]) == 0
    assert json.loads(capsys.readouterr().out)
    log = str(logs["blocks"])
    for bad in (
        ["export", log, "--format", "mcap"],
        ["export", log, "--format", "blf", "--log-layout", "blocks"],
        ["export", log, "--format", "mcap", "--log-layout", "blocks", "--out", log],
        ["export", str(tmp_path / "none.mcap"), "--format", "mcap", "--log-layout", "blocks"],
    ):
        assert cli.main(bad) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("dob-hil export: error:"), err


@pytest.mark.parametrize("source", ["samples", "blocks"])
def test_damaged_logs_convert_or_raise_log_read_error(tmp_path: Path, run_writer: Any, source: str) -> None:
    """Cuts and bit flips (a schema name, a record length, ...): the conversion gives a readable
    log or LogReadError, never another exception (a record of the wrong length is skipped)."""
    import random

    from dob_hil.errors import LogReadError

    src = tmp_path / "src.mcap"
    run_writer(src, 150, chunk_size_bytes=1024, message_layout=source, compression="none")
    blob = src.read_bytes()
    rnd = random.Random(1)
    damaged, out = tmp_path / "damaged.mcap", tmp_path / "out.mcap"
    converted = 0
    for i in range(80):
        data = bytearray(blob[: rnd.randrange(len(blob))]) if i % 2 else bytearray(blob)
        if i % 2 == 0:
            for _ in range(rnd.choice([1, 3])):
                at = rnd.randrange(len(data))
                data[at] ^= 1 << rnd.randrange(8)
        damaged.write_bytes(bytes(data))
        for target in ("samples", "blocks"):
            try:
                convert_layout(damaged, out, target)
            except LogReadError:
                continue
            read_log(out)
            converted += 1
    assert converted > 100


def test_blocks_whose_schema_was_damaged_are_skipped_with_a_warning(tmp_path: Path, run_writer: Any) -> None:
    """The sample channel's schema name damaged (``SampleBlocX``): its messages are no longer known
    as blocks, and as samples they have the wrong length: skipped, named, the rest converted."""
    src = tmp_path / "src.mcap"
    run_writer(src, 100, message_layout="blocks")
    whole = read_log(src)
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(src.read_bytes().replace(b"dob_hil/msg/SampleBlock", b"dob_hil/msg/SampleBlocX"))
    out = tmp_path / "out.mcap"
    for target in ("blocks", "samples"):
        result = convert_layout(damaged, out, target)
        assert any("wrong length" in w for w in result.warnings), result.warnings
        converted = read_log(out)
        assert len(converted.samples) == 0
        assert converted.truth.tobytes() == whole.truth.tobytes()
        assert converted.frames.tobytes() == whole.frames.tobytes()


def test_attachments_keep_their_media_types(tmp_path: Path) -> None:
    """The conversion types attachments as the writer does (a .txt one was octet-stream)."""
    from mcap.reader import make_reader

    from dob_hil.log.bench import PAPER_LAYOUT, SyntheticRun
    from dob_hil.log.writer import LogWriter

    source = tmp_path / "source.mcap"
    attachments = {"notes.txt": b"bench 3", "design.json": b"{}", "config.toml": b"", "raw.bin": b"\x00"}
    with LogWriter(source, PAPER_LAYOUT, attachments=attachments) as log:
        run = SyntheticRun(PAPER_LAYOUT)
        for k in range(20):
            run.period(log, k)
    target = tmp_path / "target.mcap"
    convert_layout(source, target, "blocks")

    def media_types(path: Path) -> dict[str, str]:
        with path.open("rb") as f:
            return {a.name: a.media_type for a in make_reader(f).iter_attachments()}

    assert (
        media_types(target)
        == media_types(source)
        == {
            "notes.txt": "text/plain",
            "design.json": "application/json",
            "config.toml": "application/toml",
            "raw.bin": "application/octet-stream",
        }
    )
