"""Campaign runs: one table serially, on the process pool and on Dask (bit for bit in the
metrics), resume without redoing cases, crashes recorded, bit-exact rerun of a case."""

from __future__ import annotations

import math
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dob_hil.campaign.cases import generate_cases
from dob_hil.campaign.execute import run_case
from dob_hil.campaign.run import Runner, run_campaign
from dob_hil.campaign.spec import load_campaign
from dob_hil.campaign.table import read_table
from dob_hil.cli import main as cli_main

VOLATILE = ("wall_s", "log")


def _comparable(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: v for k, v in r.items() if k not in VOLATILE} for r in rows]


def _assert_same(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> None:
    assert len(a) == len(b)
    for ra, rb in zip(_comparable(a), _comparable(b), strict=True):
        assert ra.keys() == rb.keys()
        for k, va in ra.items():
            vb = rb[k]
            if isinstance(va, float) and math.isnan(va):
                assert isinstance(vb, float) and math.isnan(vb), k
            else:
                assert va == vb, (ra["case_id"], k, va, vb)  # bit for bit, not approximately


@pytest.fixture(scope="module")
def serial_rows(
    tiny_writer: Callable[[Path], Path], tmp_path_factory: pytest.TempPathFactory
) -> tuple[Path, list[dict[str, Any]]]:
    tmp = tmp_path_factory.mktemp("serial")
    spec = load_campaign(tiny_writer(tmp))
    result = run_campaign(spec, tmp / "out", Runner("serial", 1))
    return tmp, read_table(result.table_path)


def test_serial_campaign_table(serial_rows: tuple[Path, list[dict[str, Any]]]) -> None:
    tmp, rows = serial_rows
    assert [r["case_id"] for r in rows] == [f"c{i:06d}" for i in range(6)]
    assert all(r["exit_reason"] == "completed" and r["error"] == "" for r in rows)
    assert all(r["tracking_error_rms"] > 0 and r["truth_samples"] > 0 for r in rows)
    # the worst case's log is kept (re-run), nothing else
    kept = sorted(p.name for p in (tmp / "out" / "logs").glob("*.mcap"))
    worst = max(rows, key=lambda r: r["tracking_error_rms"])
    assert kept == [f"{worst['case_id']}.mcap"]


def test_pool_gives_the_same_table(
    tiny_writer: Callable[[Path], Path], serial_rows: tuple[Path, list[dict[str, Any]]], tmp_path: Path
) -> None:
    spec = load_campaign(tiny_writer(tmp_path))
    result = run_campaign(spec, tmp_path / "out", Runner("pool", 2))
    assert result.batches == 3
    _assert_same(read_table(result.table_path), serial_rows[1])


def test_dask_local_cluster_gives_the_same_table(
    tiny_writer: Callable[[Path], Path], serial_rows: tuple[Path, list[dict[str, Any]]], tmp_path: Path
) -> None:
    pytest.importorskip("distributed")
    spec = load_campaign(tiny_writer(tmp_path))
    result = run_campaign(spec, tmp_path / "out", Runner("dask", 2))
    _assert_same(read_table(result.table_path), serial_rows[1])


def test_resume_does_not_redo_finished_cases(
    tiny_writer: Callable[[Path], Path], serial_rows: tuple[Path, list[dict[str, Any]]], tmp_path: Path
) -> None:
    spec = load_campaign(tiny_writer(tmp_path))
    out = tmp_path / "out"
    out.mkdir()
    src = serial_rows[0] / "out" / "journal.jsonl"
    lines = src.read_text().splitlines()
    # header + 2 finished cases + a torn last line (the write a kill interrupted)
    (out / "journal.jsonl").write_text("\n".join(lines[:3]) + "\n" + lines[3][:25])
    result = run_campaign(spec, out, Runner("serial", 1))
    assert (result.resumed, result.ran) == (2, 4)
    _assert_same(read_table(result.table_path), serial_rows[1])


def test_journal_of_another_campaign_is_refused(
    tiny_writer: Callable[[Path], Path], serial_rows: tuple[Path, list[dict[str, Any]]], tmp_path: Path
) -> None:
    from dob_hil.errors import ConfigError

    path = tiny_writer(tmp_path)
    path.write_text(path.read_text().replace("seed = 11", "seed = 12"))
    shutil.copytree(serial_rows[0] / "out", tmp_path / "out")
    with pytest.raises(ConfigError, match="another campaign"):
        run_campaign(load_campaign(path), tmp_path / "out", Runner("serial", 1))


def test_a_crashing_case_is_a_failure_row(
    tiny_writer: Callable[[Path], Path], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    from dob_hil.loop import session

    real = session.run_session

    def flaky(config: Any, options: Any) -> Any:
        if options.dob_enabled is False:
            raise RuntimeError("boom in the case")
        return real(config, options)

    monkeypatch.setattr(session, "run_session", flaky)
    spec = load_campaign(tiny_writer(tmp_path))
    result = run_campaign(spec, tmp_path / "out", Runner("serial", 1))
    rows = read_table(result.table_path)
    assert len(rows) == 6
    for r in rows:
        if r["dob_enabled"]:
            assert r["exit_reason"] == "completed" and r["stable"]
        else:
            assert r["exit_reason"] == "crash" and r["error"] == "RuntimeError: boom in the case"
            assert not r["stable"] and math.isnan(r["tracking_error_rms"])


def test_rerun_is_bit_exact(tiny_writer: Callable[[Path], Path], tmp_path: Path) -> None:
    from dob_hil.analysis.loaded import load_log

    spec = load_campaign(tiny_writer(tmp_path))
    case = generate_cases(spec)[3]
    a = run_case(spec, case, tmp_path / "a", keep_log=True)
    b = run_case(spec, case, tmp_path / "b", keep_log=True)
    _assert_same([a], [b])
    la, lb = load_log(Path(a["log"])), load_log(Path(b["log"]))
    assert len(la.data.samples) == 333
    for name in la.data.samples.dtype.names or ():
        if name == "compute_ns":
            continue  # host clock readings, not results
        assert np.array_equal(la.data.samples[name], lb.data.samples[name]), name
    assert len(la.data.truth) > 0 and la.data.truth.tobytes() == lb.data.truth.tobytes()  # the plant's truth


def test_cli_rerun_matches_the_table(
    serial_rows: tuple[Path, list[dict[str, Any]]], capsys: pytest.CaptureFixture[str]
) -> None:
    tmp = serial_rows[0]
    status = cli_main(["campaign", str(tmp / "tiny.toml"), "--out", str(tmp / "out"), "--rerun", "c000004"])
    assert status == 0
    out = capsys.readouterr().out
    assert "identical to the table's row" in out
    assert (tmp / "out" / "rerun" / "c000004.mcap").is_file()


def test_cli_bad_input_is_one_line(
    tiny_writer: Callable[[Path], Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli_main(["campaign", str(tmp_path / "missing.toml")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no such campaign file" in err
    path = tiny_writer(tmp_path)
    assert cli_main(["campaign", str(path), "--rerun", "c999999", "--out", str(tmp_path / "o")]) == 2
    assert "no case 'c999999'" in capsys.readouterr().err


def test_dask_existing_scheduler_by_address(
    tiny_writer: Callable[[Path], Path], serial_rows: tuple[Path, list[dict[str, Any]]], tmp_path: Path
) -> None:
    """``--scheduler ADDRESS``: the campaign connects to a cluster it did not start."""
    distributed = pytest.importorskip("distributed")
    spec = load_campaign(tiny_writer(tmp_path))
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None) as cluster:
        result = run_campaign(spec, tmp_path / "out", Runner("dask", 2, cluster.scheduler_address))
    _assert_same(read_table(result.table_path), serial_rows[1])
