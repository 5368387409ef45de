"""The command line: pipes, output paths, design files, init/config, progress bar, summary text."""

from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

import pytest

from dob_hil import cli
from dob_hil.commands.progress import ProgressBar
from dob_hil.commands.run import format_summary
from dob_hil.config import load_config, parse_config_text
from dob_hil.scenarios import scenario_path


@pytest.fixture(scope="module")
def short_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("log")
    path = out / "step.mcap"
    assert (
        cli.main(
            ["run", "--scenario", "paper-step", "--duration", "0.05", "--log", str(path), "--no-progress"]
        )
        == 0
    )
    return path


def _closed_pipe(argv: list[str]) -> tuple[int, str]:
    """Run ``dob-hil argv`` with its stdout a pipe whose reader has gone (``| head`` after exit)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "dob_hil.cli", *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()
    err = proc.stderr.read().decode()
    return proc.wait(timeout=300), err


@pytest.mark.parametrize("command", ["run", "analyze", "design"])
def test_a_closed_pipe_ends_quietly(command: str, short_log: Path, tmp_path: Path) -> None:
    argv = {
        "run": ["run", "--scenario", "paper-step", "--duration", "0.02", "--log", str(tmp_path / "r.mcap")],
        "analyze": ["analyze", str(short_log), "--from", "0", "--no-plots"],
        "design": ["design", "paper-step", "--no-plots", "--out", str(tmp_path / "d")],
    }[command]
    rc, err = _closed_pipe(argv)
    assert "Traceback" not in err and "BrokenPipe" not in err, err
    assert rc == 141
    if command == "run":  # the run itself completed and its log is whole
        assert (tmp_path / "r.mcap").stat().st_size > 0


def test_output_paths_that_are_files_are_one_line(
    short_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    a_file = tmp_path / "plots.png"
    a_file.write_text("x")
    assert cli.main(["analyze", str(short_log), "--from", "0", "--plots", str(a_file)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("dob-hil analyze: error: --plots:") and "is a file" in err
    assert cli.main(["design", "paper-step", "--out", str(a_file)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("dob-hil design: error: --out:") and "is a file" in err
    assert cli.main(["design", "paper-step", "--out", str(a_file / "sub")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("dob-hil design: error: --out:") and len(err.strip().splitlines()) == 1


def test_replay_takes_a_design_file(
    short_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli.main(["design", "paper-sine", "--no-plots", "--out", str(tmp_path / "d")]) == 0
    capsys.readouterr()
    design_json = tmp_path / "d" / "design.json"
    assert cli.main(["replay", str(short_log), "--design", str(design_json), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["mode"] == "design" and out["samples"] > 0
    # the same design from its config gives the same commands
    assert cli.main(["replay", str(short_log), "--design", "paper-sine", "--json"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert again["u_cmd_diff_rms_A"] == out["u_cmd_diff_rms_A"]
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "something else"}')
    assert cli.main(["replay", str(short_log), "--design", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "design JSON" in err and "TOML" not in err


def test_init_writes_a_starter_that_designs_and_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "mine.toml"
    assert cli.main(["init", str(path)]) == 0
    text = path.read_text()
    assert text.count("\n#") > 40  # commented: every key has its line
    assert cli.main(["init", str(path)]) == 2  # never overwritten
    assert "exists" in capsys.readouterr().err
    assert cli.main(["design", str(path), "--no-plots", "--out", str(tmp_path / "d")]) == 0
    assert (
        cli.main(["run", str(path), "--duration", "0.02", "--log", str(tmp_path / "m.mcap"), "--no-progress"])
        == 0
    )
    cfg = load_config(path)
    assert cfg.name == "my-motor"


def test_config_template_and_doc_on_stdout(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["config", "--template"]) == 0
    parse_config_text(capsys.readouterr().out)
    assert cli.main(["config", "--doc"]) == 0
    doc = capsys.readouterr().out
    assert "`current_limit_A` | number | A | `0.7` | > 0, <= 1000 |" in doc


def test_run_help_states_the_defaults(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        cli.main(["run", "--help"])
    out = capsys.readouterr().out
    for option in ("--duration", "--log", "--no-dob"):
        line = out[out.index(option) :].split("\n  -")[0]
        assert "default" in line, line


# --- progress bar --------------------------------------------------------------------------------
class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_bar_is_silent_off_a_terminal() -> None:
    stream = io.StringIO()
    bar = ProgressBar("x", stream=stream, delay_s=0.0, max_rate_hz=1e9)
    bar(10, 100)
    bar.finish(100, 100)
    assert stream.getvalue() == "" and not bar.enabled


def test_progress_bar_fits_the_width_shows_an_eta_and_ends_at_100() -> None:
    now = [0.0]
    stream = _Tty()
    bar = ProgressBar(
        "paper-step (no DOB)", stream=stream, delay_s=0.5, max_rate_hz=10.0, clock=lambda: now[0]
    )
    bar(1, 100)  # before the delay: nothing (a short run prints no bar)
    assert stream.getvalue() == ""
    now[0] = 1.0
    bar(25, 100)
    first = stream.getvalue()
    assert "25.0%" in first and "ETA 0:03" in first  # 75 more at 25 per second
    now[0] = 4.0
    bar.finish(100, 100)
    final = stream.getvalue().split("\r")[-1]
    assert "100.0%" in final and final.endswith("\n")
    for width in (20, 40, 80, 200):
        line = bar.line(50, 100, 2.0, width)
        assert len(line) <= width and "50.0%" in line


def test_progress_bar_appears_for_a_short_long_run(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """No fixed duration threshold: the bar is offered for any run (it draws after 0.5 s wall)."""
    from dob_hil.commands import run as run_cmd

    seen: list[object] = []
    real = run_cmd.ProgressBar if hasattr(run_cmd, "ProgressBar") else None
    assert real is None  # the bar lives in dob_hil.commands.progress

    from dob_hil.commands import progress

    class Spy(progress.ProgressBar):
        @property
        def enabled(self) -> bool:
            return True

        def __call__(self, done: int, total: int) -> None:
            seen.append((done, total))

    orig = progress.ProgressBar
    progress.ProgressBar = Spy  # type: ignore[misc]
    try:
        assert (
            cli.main(
                ["run", "--scenario", "paper-step", "--duration", "2", "--log", str(tmp_path / "p.mcap")]
            )
            == 0
        )
    finally:
        progress.ProgressBar = orig  # type: ignore[misc]
    assert seen and all(total == 6667 for _, total in seen)  # type: ignore[misc]


# --- run summary text ------------------------------------------------------------------------------
def _summary(**kw: object) -> dict[str, object]:
    d: dict[str, object] = {
        "name": "x", "exit_reason": "completed", "mode": "lockstep", "dob_enabled": True, "samples": 1,
        "planned_samples": 1, "duration_s": 0.0003, "wall_time_s": 0.01, "samples_per_s": 100.0,
        "max_abs_current_A": 0.1, "current_limit_A": 0.7, "saturated_samples": 1, "missing_samples": 1,
        "skipped_samples": 0, "overruns": 1, "compute_ns_max": 5000, "log_path": "x.mcap",
        "log_dropped_records": 0, "events": {}, "rt_refused": [],
    }  # fmt: skip
    d.update(kw)
    return d


def test_summary_words_counts_and_clock() -> None:
    text = format_summary(_summary())
    assert "1 samples" not in text and "saturated 1 sample," not in text
    assert "saturated 1 sample" in text and "missing 1 sample " in text and "1 overrun" in text
    assert "s simulated" in text
    rt = format_summary(_summary(mode="realtime", samples=2, saturated_samples=2))
    assert "simulated" not in rt and "s run time" in rt and "saturated 2 samples" in rt
    assert "skipped" not in rt  # "skipped" is analyze's word (log gaps explained by events)


def test_shipped_scenarios_are_commented_examples() -> None:
    for name in ("paper-step", "paper-sine"):
        text = scenario_path(name).read_text()
        comments = [line for line in text.splitlines() if line.lstrip().startswith("#") or " # " in line]
        assert len(comments) >= 15, name
