"""Measurements of the log: pack cost per call, bytes per sample, read throughput, kill -9 loss.

``python -m dob_hil.log.bench [--samples N] [--out DIR]`` prints the figures. The synthetic run
(:func:`write_synthetic`) is also what the tests write: a noisy servo-like trajectory, one
sample, two CAN frames (feedback rx, command tx) and one ground-truth record per period.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import resource
import sys
import tempfile
import time
from pathlib import Path

from dob_hil.log.metadata import run_metadata
from dob_hil.log.reader import read_log
from dob_hil.log.schemas import FLAG_DOB_ON, LogLayout
from dob_hil.log.writer import LogWriter

PAPER_LAYOUT = LogLayout(n_states=2, n_inputs=1, n_outputs=1, n_plant_states=2)
PERIOD_NS = 300_000


class SyntheticRun:
    """Deterministic, realistic-looking records for period ``k`` (noisy floats do not compress)."""

    def __init__(self, layout: LogLayout = PAPER_LAYOUT, seed: int = 1) -> None:
        self.layout = layout
        self.rng = random.Random(seed)

    def period(self, log: LogWriter, k: int, truth: bool = True, frames: bool = True) -> None:
        lay, rng = self.layout, self.rng
        t = k * PERIOD_NS
        rx = t + 20_000 + rng.randrange(0, 60_000)
        tx = rx + 15_000 + rng.randrange(0, 5_000)
        pos = math.sin(k * 1e-3) + rng.gauss(0.0, 1e-4)
        counts = round(pos * 4096)
        x_ref = [math.sin(k * 1e-3 + i) for i in range(lay.n_states)]
        x_hat = [v + rng.gauss(0.0, 1e-3) for v in x_ref]
        x_bar = [v + rng.gauss(0.0, 1e-4) for v in x_hat]
        u_fb = [0.3 * math.cos(k * 1e-3) + rng.gauss(0.0, 1e-2) for _ in range(lay.n_inputs)]
        u_dist = [rng.gauss(0.05, 1e-3) for _ in range(lay.n_inputs)]
        u_cmd = [a + b for a, b in zip(u_fb, u_dist, strict=True)]
        dac = [round(v * 1000) for v in u_cmd]
        log.sample(
            t, rx, tx, rx - t, [counts] * lay.n_outputs, [counts / 4096] * lay.n_outputs,
            x_ref, x_hat, x_bar, u_fb, u_dist, u_cmd, [d / 1000 for d in dac],
            k, 1_000 + rng.randrange(500), dac, k & 0xFF, FLAG_DOB_ON,
        )  # fmt: skip
        if frames:
            feedback = (counts & 0xFFFFFFFF).to_bytes(4, "little") + bytes([k & 0xFF, 1])
            log.frame_raw(rx, 0x181, True, 6, feedback, 0)
            log.frame_raw(
                tx, 0x201, False, 3, (dac[0] & 0xFFFF).to_bytes(2, "little") + bytes([0x80 | (k & 0x7F)]), 0
            )
        if truth:
            state = [pos + rng.gauss(0.0, 1e-5) for _ in range(lay.n_plant_states)]
            log.truth(t, state, u_dist, [d / 1000 for d in dac], k, 1)
        if k % 10_000 == 0:
            log.event(t, "info", "progress", f"sample {k}", {"k": k})


def write_synthetic(
    path: Path,
    n_samples: int,
    *,
    truth: bool = True,
    pace_backlog_bytes: int = 8 << 20,
    **writer_options: object,
) -> LogWriter:
    """Write ``n_samples`` periods as fast as the writer process takes them; returns the closed writer."""
    run = SyntheticRun()
    meta = {"run": run_metadata(mode="synthetic", bus="none", period_ns=PERIOD_NS, layout=PAPER_LAYOUT)}
    with LogWriter(path, PAPER_LAYOUT, metadata=meta, **writer_options) as log:  # type: ignore[arg-type]
        for k in range(n_samples):
            run.period(log, k, truth)
            log.flush()
            if k % 1000 == 0:
                while log.stats.backlog_bytes > pace_backlog_bytes:
                    time.sleep(0.005)
                    log.flush(force=True)
    return log


def _percentile(sorted_ns: list[int], q: float) -> float:
    return sorted_ns[min(len(sorted_ns) - 1, int(q * len(sorted_ns)))] / 1000.0


def measure_pack(tmp: Path, n: int = 200_000) -> dict[str, float]:
    """Per-call cost of sample() and of one full period (sample + 2 frames + flush), in us."""
    run = SyntheticRun()
    args = []
    with LogWriter(tmp / "pack.mcap", PAPER_LAYOUT) as log:
        values = (1.0, 2.0)
        clock = time.perf_counter_ns
        sample_ns: list[int] = []
        period_ns: list[int] = []
        for k in range(n):
            t = k * PERIOD_NS
            args = [t, t + 5, t + 9, 5, (k,), (0.5,), values, values, values, (0.1,), (0.2,), (0.3,), (0.3,)]
            t0 = clock()
            log.sample(*args, k, 1200, (k & 0xFFF,), k & 0xFF, FLAG_DOB_ON)  # type: ignore[arg-type,call-arg]
            t1 = clock()
            log.frame_raw(t + 5, 0x181, True, 6, b"\x01\x02\x03\x04\x05\x06", 0)
            log.frame_raw(t + 9, 0x201, False, 3, b"\x01\x02\x03", 0)
            log.flush()
            t2 = clock()
            sample_ns.append(t1 - t0)
            period_ns.append(t2 - t0)
            if k % 1000 == 0:
                while log.stats.backlog_bytes > 4 << 20:
                    time.sleep(0.002)
                    log.flush(force=True)
        del run
    sample_ns.sort()
    period_ns.sort()
    return {
        "sample_p50_us": _percentile(sample_ns, 0.5),
        "sample_p99_us": _percentile(sample_ns, 0.99),
        "sample_max_us": sample_ns[-1] / 1000.0,
        "period_p50_us": _percentile(period_ns, 0.5),
        "period_p99_us": _percentile(period_ns, 0.99),
        "period_max_us": period_ns[-1] / 1000.0,
    }


def measure_size(tmp: Path, n: int = 200_000) -> dict[str, float]:
    """Bytes on disk per sample: samples only (all overhead included), and a full period."""
    out: dict[str, float] = {}
    for compression in ("zstd", "none"):
        path = tmp / f"size-{compression}.mcap"
        run = SyntheticRun()
        with LogWriter(path, PAPER_LAYOUT, compression=compression) as log:
            for k in range(n):
                run.period(log, k, truth=False, frames=False)
                log.flush()
        out[f"samples_only_{compression}_B"] = path.stat().st_size / n
        path.unlink()
    for message_layout in ("samples", "blocks"):
        path = tmp / f"size-full-{message_layout}.mcap"
        write_synthetic(path, n, message_layout=message_layout)
        key = "full_period_zstd_B" if message_layout == "samples" else "full_period_blocks_zstd_B"
        out[key] = path.stat().st_size / n
        path.unlink()
    return out


def measure_read(tmp: Path, n: int, baseline_messages: int = 300_000) -> dict[str, float]:
    """read_log throughput on an ``n``-sample log (2 frames per sample) vs the mcap library."""
    path = tmp / "read.mcap"
    t0 = time.perf_counter()
    write_synthetic(path, n, truth=False)
    write_s = time.perf_counter() - t0
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    best = math.inf
    for _ in range(3):
        t0 = time.perf_counter()
        data = read_log(path)
        best = min(best, time.perf_counter() - t0)
    assert len(data.samples) == n and len(data.frames) == 2 * n, (len(data.samples), len(data.frames))
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    del data

    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    count = 0
    t0 = time.perf_counter()
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _item in reader.iter_decoded_messages(topics=["/dob_hil/sample", "/dob_hil/can"]):
            count += 1
            if count >= baseline_messages:
                break
    baseline_s = time.perf_counter() - t0
    size = path.stat().st_size
    path.unlink()
    return {
        "samples": n,
        "file_MB": size / 1e6,
        "write_s": write_s,
        "read_s": best,
        "read_samples_per_s": n / best,
        "read_messages_per_s": 3 * n / best,
        "baseline_messages_per_s": count / baseline_s,
        "baseline_samples_per_s": count / baseline_s / 3,
        "max_rss_MB_after_read": rss1 / 1024,
        "max_rss_MB_before_read": rss0 / 1024,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dob_hil.log.bench", description=__doc__)
    parser.add_argument("--samples", type=int, default=1_000_000, help="samples of the read benchmark log")
    parser.add_argument("--out", type=Path, default=None, help="directory for the scratch logs")
    parser.add_argument("--only", choices=("pack", "size", "read"), default=None)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(dir=args.out) as tmp_name:
        tmp = Path(tmp_name)
        report: dict[str, object] = {"cpus": os.cpu_count(), "python": sys.version.split()[0]}
        if args.only in (None, "pack"):
            report["pack"] = measure_pack(tmp)
        if args.only in (None, "size"):
            report["size"] = measure_size(tmp)
        if args.only in (None, "read"):
            report["read"] = measure_read(tmp, args.samples)
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
