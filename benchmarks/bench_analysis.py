"""Analysis read throughput beside decoding baselines, and the peak memory of analysing a 1-hour log.

On a synthetic log (``dob_hil.log.bench.write_synthetic``: per 300 us period one sample, two CAN
frames and one ground-truth record; noisy floats), same run:

- ``read_log`` of the whole log, and of the sample channel only (samples/s, median of repeats);
- the analysis metrics: ``dob_hil.analysis`` ``load_log`` + ``derive_signals`` +
  ``compute_metrics`` (what ``dob-hil analyze --no-plots`` computes), samples/s;
- the mcap library's plain reader (``make_reader(f).iter_messages()``, no decoding) over every
  message of the same log, timed in the same run: ``ratio_read_log_vs_mcap_plain`` is read_log's
  messages/s over the plain reader's (goal > 20);
- baselines decoding the same samples message by message: the mcap library's iteration with
  the ros2 (CDR) decoder of ``mcap-ros2-support`` on this log, and the mcap library's iteration
  + ``json.loads`` on a JSON-encoded MCAP of the same sample values (both on at most
  ``--baseline-samples``; their rate does not depend on the log's length).

``--hour``: a 12 M-sample log (1 hour at 3.33 kHz, ~2.8 GB; generated once, minutes, and cached
as ``<cache-dir>/synthetic-<N>.mcap``), analysed by ``dob-hil analyze --no-plots --json`` and read
by ``read_log`` alone, each in a child process whose peak RSS comes from ``os.wait4``.

``--verify LOG`` (a real run's log: replay needs its design): ``dob-hil replay LOG --verify`` in a
child process (wall time, peak RSS), and the streamed verification alone in this process
(samples/s without the interpreter's start).

Goals: read >= 1,000,000 samples/s and > 20x the mcap plain reader; analysing the 1-hour log in
<= 500 MB (streamed, as for an 8-hour log); ``replay --verify`` >= 500,000 samples/s in a memory
independent of the log's length.

    .venv/bin/python benchmarks/bench_analysis.py [--smoke] [--json] [--samples N]
    .venv/bin/python benchmarks/bench_analysis.py --hour [--hour-samples N] [--cache-dir DIR]
    .venv/bin/python benchmarks/bench_analysis.py --verify LOG.mcap
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from _common import parser, report

from dob_hil.log import read_log
from dob_hil.log.bench import write_synthetic
from dob_hil.log.schemas import TOPIC_SAMPLE

READ_GOAL_PER_S = 1_000_000
RSS_GOAL_BYTES = 500 * 1000**2  # analyze is streamed: an 8-hour log in <= 500 MB (issue 16)
DEFAULT_CACHE = Path(tempfile.gettempdir()) / "dob-hil-bench"


def cached_log(n: int, cache_dir: Path) -> tuple[Path, float | None]:
    """The synthetic ``n``-sample log, written once (returns the path and the write time, if written)."""
    cache_dir.mkdir(parents=True, exist_ok=True)
    path = cache_dir / f"synthetic-{n}.mcap"
    if path.exists():
        return path, None
    partial = cache_dir / f".synthetic-{n}-{os.getpid()}.mcap"
    t0 = time.perf_counter()
    write_synthetic(partial, n)
    elapsed = time.perf_counter() - t0
    partial.replace(path)
    return path, elapsed


def timed(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    """Median wall time of ``repeats`` calls and the last result."""
    times, result = [], None
    for _ in range(repeats):
        result = None  # the previous result's memory is free before the next call
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), result


def analysis_fn(path: Path) -> tuple[Callable[[], Any] | None, str]:
    """The analysis pipeline of ``dob-hil analyze --no-plots`` if the package has it."""
    try:
        from dob_hil.analysis.loaded import load_log
        from dob_hil.analysis.metrics import compute_metrics
        from dob_hil.analysis.signals import derive_signals
    except ImportError as exc:
        return None, f"dob_hil.analysis not available ({exc}): read_log alone"

    def run() -> Any:
        log = load_log(path)
        return compute_metrics(log, 0.1, derive_signals(log))

    return run, "load_log + derive_signals + compute_metrics"


def ros2_baseline(path: Path, limit: int) -> tuple[int, float]:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    count = 0
    t0 = time.perf_counter()
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _schema, _channel, _message, decoded in reader.iter_decoded_messages(topics=[TOPIC_SAMPLE]):
            count += 1
            del decoded
            if count >= limit:
                break
    return count, time.perf_counter() - t0


def write_json_mcap(path: Path, samples: np.ndarray[Any, Any]) -> None:
    """The given samples as a JSON-encoded MCAP (one JSON object per sample, arrays as lists)."""
    from mcap.writer import Writer

    names = samples.dtype.names or ()
    with path.open("wb") as f:
        w = Writer(f)
        w.start()
        schema = w.register_schema("dob_hil/SampleJson", "jsonschema", b'{"type": "object"}')
        ch = w.register_channel(TOPIC_SAMPLE, "json", schema)
        columns = {name: samples[name].tolist() for name in names}
        for i in range(len(samples)):
            obj = {name: columns[name][i] for name in names}
            t = int(obj["time_ns"])
            w.add_message(ch, t, json.dumps(obj).encode(), t, i)
        w.finish()  # type: ignore[no-untyped-call]


def plain_baseline(path: Path, limit: int) -> tuple[int, float]:
    """The mcap library's plain reader: every message, not decoded (at most ``limit``)."""
    from mcap.reader import make_reader

    count = 0
    t0 = time.perf_counter()
    with path.open("rb") as f:
        for _item in make_reader(f).iter_messages():
            count += 1
            if count >= limit:
                break
    return count, time.perf_counter() - t0


def verify_child(path: Path) -> dict[str, Any]:
    """replay --verify of a real log: the command in a child (wall, peak RSS), and in process."""
    from dob_hil.analysis.loaded import load_log
    from dob_hil.analysis.verify_fast import verify_streaming
    from dob_hil.log.schemas import TOPIC_EVENT

    child = child_peak([*dob_hil_command(), "replay", str(path), "--verify", "--json"])
    t0 = time.perf_counter()
    log = load_log(path, topics=[TOPIC_EVENT])
    t1 = time.perf_counter()
    result = verify_streaming(log)
    t2 = time.perf_counter()
    if result is None or not result.identical:
        raise RuntimeError(f"{path}: not verified identical by the streamed path")
    from dob_hil.analysis.replay import verify

    full = load_log(path)
    t3 = time.perf_counter()
    chained = verify(full)
    t4 = time.perf_counter()
    del full
    return {
        "log": str(path),
        "samples": result.samples,
        "file_MB": round(path.stat().st_size / 1e6, 1),
        "command": child,
        "command_samples_per_s": round(result.samples / child["seconds"]),
        "streamed_verify_samples_per_s": round(result.samples / (t2 - t1)),
        "events_and_metadata_read_s": round(t1 - t0, 2),
        "chained_verify_samples_per_s": round(chained.samples / (t4 - t3)),
        "speedup_streamed_vs_chained": round((t4 - t3) / (t2 - t1), 1),
        "goal_ge_500k_per_s_met": result.samples / (t2 - t1) >= 500_000,
    }


def json_baseline(path: Path) -> tuple[int, float]:
    from mcap.reader import make_reader

    count = 0
    t0 = time.perf_counter()
    with path.open("rb") as f:
        for _schema, _channel, message in make_reader(f).iter_messages(topics=[TOPIC_SAMPLE]):
            obj = json.loads(message.data)
            count += 1
            del obj
    return count, time.perf_counter() - t0


def throughput(args: Any) -> dict[str, Any]:
    n = args.samples or (20_000 if args.smoke else 1_000_000)
    repeats = 2 if args.smoke else 3
    with tempfile.TemporaryDirectory(prefix="bench-analysis-") as tmp_name:
        tmp = Path(tmp_name)
        path, write_s = cached_log(n, tmp if args.smoke else args.cache_dir)
        out: dict[str, Any] = {"samples": n, "log": str(path), "file_MB": round(path.stat().st_size / 1e6, 1)}
        if write_s is not None:
            out["log_written_in_s"] = round(write_s, 1)
        t_all, data = timed(lambda: read_log(path), repeats)
        if len(data.samples) != n or not data.complete:
            raise RuntimeError(f"{path}: {len(data.samples)} samples, complete={data.complete}: stale cache?")
        some = data.samples[: min(n, args.baseline_samples)].copy()
        del data
        t_samples, _ = timed(lambda: read_log(path, topics=[TOPIC_SAMPLE]), repeats)
        read = {
            "all_channels": round(n / t_all),
            "sample_channel_only": round(n / t_samples),
        }
        fn, what = analysis_fn(path)
        analysis: dict[str, Any] = {"what": what}
        if fn is not None:
            t_an, metrics = timed(fn, max(1, repeats - 1))
            analysis["samples_per_s"] = round(n / t_an)
            analysis["seconds"] = round(t_an, 3)
            analysis["metrics_samples"] = metrics["samples"]
        ros2_n, ros2_s = ros2_baseline(path, args.baseline_samples)
        plain_n, plain_s = plain_baseline(path, 4 * args.baseline_samples)
        json_path = tmp / "samples-json.mcap"
        write_json_mcap(json_path, some)
        json_n, json_s = json_baseline(json_path)
    baseline = {
        "mcap_iter_ros2_decoder": round(ros2_n / ros2_s),
        "mcap_iter_json_loads": round(json_n / json_s),
        "messages_each": min(ros2_n, json_n),
        "mcap_plain_reader_messages_per_s": round(plain_n / plain_s),
    }
    messages_per_sample = 4  # sample, two frames, truth
    out.update(
        {
            "read_log_samples_per_s": read,
            "analysis": analysis,
            "baseline_samples_per_s": baseline,
            "speedup_read_log_vs_json": round(read["all_channels"] / baseline["mcap_iter_json_loads"], 1),
            "speedup_read_log_vs_ros2": round(read["all_channels"] / baseline["mcap_iter_ros2_decoder"], 1),
            "ratio_read_log_vs_mcap_plain": round(
                read["all_channels"] * messages_per_sample / baseline["mcap_plain_reader_messages_per_s"], 1
            ),
            "goal_read_ge_1M_per_s_met": read["all_channels"] >= READ_GOAL_PER_S,
        }
    )
    return out


def child_peak(cmd: list[str]) -> dict[str, Any]:
    """Run ``cmd``; its wall time, exit status and peak RSS (ru_maxrss of this child alone)."""
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, stderr=err)
        _pid, status, usage = os.wait4(proc.pid, 0)
        seconds = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        stdout_bytes = out.seek(0, 2)
        err.seek(0)
        stderr = err.read().decode(errors="replace")
    return {
        "exit_status": proc.returncode,
        "seconds": round(seconds, 1),
        "peak_rss_MB": round(usage.ru_maxrss / 1024, 1),  # ru_maxrss is in KiB on Linux
        "peak_rss_bytes": usage.ru_maxrss * 1024,
        "stderr_tail": stderr.strip().splitlines()[-3:],
        "stdout_bytes": stdout_bytes,
    }


def dob_hil_command() -> list[str]:
    script = Path(sys.executable).with_name("dob-hil")
    return [str(script)] if script.exists() else [sys.executable, "-m", "dob_hil.cli"]


def hour(args: Any) -> dict[str, Any]:
    n = args.hour_samples
    print(f"bench_analysis: {n} samples log in {args.cache_dir} (written once; minutes)", file=sys.stderr)
    path, write_s = cached_log(n, args.cache_dir)
    read_code = (
        "import sys; from dob_hil.log import read_log; d = read_log(sys.argv[1]); "
        "print(len(d.samples), len(d.frames), len(d.truth))"
    )
    read = child_peak([sys.executable, "-c", read_code, str(path)])
    analyze = child_peak([*dob_hil_command(), "analyze", "--no-plots", "--json", str(path)])
    return {
        "samples": n,
        "log": str(path),
        "file_MB": round(path.stat().st_size / 1e6, 1),
        "log_written_in_s": None if write_s is None else round(write_s, 1),
        "read_log_child": read,
        "dob_hil_analyze_child": analyze,
        "goal_analyze_le_500MB_met": analyze["exit_status"] == 0
        and analyze["peak_rss_bytes"] <= RSS_GOAL_BYTES,
    }


def main() -> None:
    p = parser(__doc__ or "")
    p.add_argument("--samples", type=int, help="samples of the throughput log (default 1e6, smoke 2e4)")
    p.add_argument("--baseline-samples", type=int, default=100_000, help="samples decoded by the baselines")
    p.add_argument("--hour", action="store_true", help="the 1-hour (12 M samples) memory benchmark instead")
    p.add_argument("--hour-samples", type=int, default=12_000_000, help="samples of the --hour log")
    p.add_argument("--cache-dir", type=Path, default=DEFAULT_CACHE, help="where generated logs are kept")
    p.add_argument("--verify", type=Path, metavar="LOG", help="replay --verify throughput and memory on LOG")
    args = p.parse_args()
    if args.verify:
        report("analysis: replay --verify", verify_child(args.verify), args.json)
        return
    if args.hour:
        result = hour(args)
        name = "analysing a 1-hour log: peak RSS"
    else:
        result = throughput(args)
        name = "analysis read throughput vs decoding baselines"
    result["goal"] = "read >= 1,000,000 samples/s; analysing a long log (streamed) in <= 500 MB"
    report(name, result, args.json)


if __name__ == "__main__":
    main()
