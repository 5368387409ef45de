"""Shared parts of the real-time benchmarks: a standalone drive, the bare round trip, log figures.

- :func:`udp_channel`: a random multicast group of 239.74.163.0/24 that python-can can open.
- :func:`node_config`: paper-step with its own node id (every process on the machine shares the
  udp_multicast port, so concurrent runs are told apart by node id) and, optionally, wider
  watchdog/host timeouts so that a VM stall of a loaded machine does not end the run.
- :func:`standalone_drive`: ``python -m firmware_sim CONFIG -i udp_multicast -c GROUP`` in its
  own process, stderr to a file (a pipe nobody reads could fill and stall the drive).
- :func:`bare_round_trip`: ping-pong with :mod:`udp_echo` in another process on the same
  interface, paced at the control period: the transport's own cost, to set the loop's beside.
- :func:`timing_figures` and :func:`accounting`: what a real-time log says about overruns,
  latency, lateness and completeness.
"""

from __future__ import annotations

import json
import os
import random
import secrets
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
from _common import percentiles

from dob_hil.log import LogData
from dob_hil.log.schemas import FLAG_FEEDBACK_MISSING, FLAG_OVERRUN
from dob_hil.scenarios import scenario_variant
from firmware_sim import process
from firmware_sim.process import StandaloneDrive

BENCH_DIR = Path(__file__).resolve().parent
REPO_ROOT = BENCH_DIR.parent
SKIP_STATUS = 77  # "cannot be measured here" (automake's convention); the smoke test skips on it
SKIP_EVENT_KINDS = ("feedback_lost", "overrun_skip")


class Unavailable(Exception):
    """The benchmark cannot run on this machine (no udp_multicast); the message says why."""


def skip(reason: str) -> None:
    print(f"skipped: {reason}")
    sys.exit(SKIP_STATUS)


def private_udp_port() -> int:
    """Move this process's and its children's udp_multicast buses to a random port of their own.

    python-can binds every udp_multicast bus to ``("", port)``, so on the default port 43113 each
    socket also receives every other group's traffic on the machine (other test runs included).
    The port goes into python-can's ``CAN_CONFIG`` environment variable, which ``can.Bus`` (and
    so ``dob_hil.link.bus.open_bus`` and ``python -m firmware_sim``) reads for options not given.
    """
    port = random.randint(43200, 43999)
    config = json.loads(os.environ.get("CAN_CONFIG", "{}") or "{}")
    config["port"] = port
    os.environ["CAN_CONFIG"] = json.dumps(config)
    return port


def udp_channel() -> str:
    try:
        return process.free_udp_multicast_channel()
    except RuntimeError as exc:
        raise Unavailable(str(exc)) from exc


def node_config(directory: Path, node_id: int, patience_periods: int | None) -> Path:
    """paper-step with ``node_id``; watchdog and host timeout widened to ``patience_periods``."""
    return scenario_variant("paper-step", directory, node_id=node_id, patience_periods=patience_periods)


def child_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO_ROOT), env.get("PYTHONPATH", "")) if p)
    return env


def _pin(pid: int, cpu: int | None) -> None:
    """Pin a just-started child to ``cpu``: the threads it starts later inherit the affinity."""
    if cpu is not None:
        os.sched_setaffinity(pid, {cpu})


@contextmanager
def standalone_drive(
    config: Path,
    channel: str,
    *,
    spin_us: float | None = None,
    cpu: int | None = None,
    sched_fifo: bool = False,
) -> Iterator[StandaloneDrive]:
    """The simulated drive in its own process over udp_multicast (firmware_sim.process)."""
    with process.standalone_drive(
        config, "udp_multicast", channel, spin_us=spin_us, sched_fifo=sched_fifo,
        cpus=() if cpu is None else (cpu,), env=child_env(),
    ) as drive:  # fmt: skip
        yield drive


# --------------------------------------------------------------------------- bare round trip
@dataclass
class RoundTrip:
    rtt_ns: list[int] = field(default_factory=list)
    send_ns: list[int] = field(default_factory=list)  # the host's bus.send() call alone
    lost: int = 0

    def extend(self, other: RoundTrip) -> None:
        self.rtt_ns += other.rtt_ns
        self.send_ns += other.send_ns
        self.lost += other.lost

    def figures(self) -> dict[str, Any]:
        if not self.rtt_ns:
            return {"n": 0, "lost": self.lost}
        p = percentiles([v / 1000 for v in self.rtt_ns], (50, 99, 99.9))
        return {"n": len(self.rtt_ns), "lost": self.lost, **{k: round(v, 1) for k, v in p.items()}}

    def send_figures(self) -> dict[str, Any]:
        p = percentiles([v / 1000 for v in self.send_ns], (50, 99, 99.9)) if self.send_ns else {}
        return {k: round(v, 1) for k, v in p.items()}


def _read_line(stream: IO[str], proc: subprocess.Popen[str], timeout_s: float) -> str:
    import select

    ready, _, _ = select.select([stream], [], [], timeout_s)
    if not ready:
        raise RuntimeError(f"udp_echo did not start within {timeout_s:g} s")
    line = stream.readline()
    if not line:
        raise RuntimeError(f"udp_echo exited with status {proc.wait()}")
    return line.strip()


def bare_round_trip(
    channel: str, n: int, period_ns: int, *, cpu: int | None = None, timeout_s: float = 0.05
) -> RoundTrip:
    """``n`` ping-pongs with an echo process, one per ``period_ns``; round trip times in ns.

    A ping without its pong within ``timeout_s`` counts as lost. Times are taken with
    ``perf_counter_ns`` from before ``send`` to after the ``recv`` that returns the pong (the
    message is built before); the ``send`` call alone is timed too.
    """
    import can
    from udp_echo import PAYLOAD, PING_ID, PONG_ID, STOP_COUNTER

    token = secrets.token_bytes(4)
    echo = subprocess.Popen(
        [sys.executable, str(BENCH_DIR / "udp_echo.py"), channel, token.hex()],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=child_env(),
    )
    _pin(echo.pid, cpu)
    assert echo.stdout is not None
    bus = can.Bus(interface="udp_multicast", channel=channel, receive_own_messages=False)
    result = RoundTrip()
    clock = time.perf_counter_ns

    def ping(counter: int, wait_s: float) -> int | None:
        payload = PAYLOAD.pack(token, counter)
        out = can.Message(arbitration_id=PING_ID, is_extended_id=True, data=payload)
        t0 = clock()
        bus.send(out)
        result.send_ns.append(clock() - t0)
        end = t0 + int(wait_s * 1e9)
        while (left := end - clock()) > 0:
            got = bus.recv(left * 1e-9)
            if (
                got is not None
                and got.arbitration_id == PONG_ID
                and got.is_extended_id
                and got.data == payload
            ):
                return clock() - t0
        return None

    try:
        if _read_line(echo.stdout, echo, 30.0) != "ready":
            raise RuntimeError("udp_echo did not say ready")
        for attempt in range(200):  # until the echo's group membership is in place
            if ping(1_000_000 + attempt, 0.01) is not None:
                break
        else:
            raise RuntimeError("udp_echo never answered")
        result.send_ns.clear()
        next_ns = time.monotonic_ns()
        for i in range(n):
            next_ns += period_ns
            rtt = ping(i, timeout_s)
            if rtt is None:
                result.lost += 1
            else:
                result.rtt_ns.append(rtt)
            wait_ns = next_ns - time.monotonic_ns()
            if wait_ns > 0:
                time.sleep(wait_ns * 1e-9)
            else:
                next_ns = time.monotonic_ns()  # fell behind: no burst
        bus.send(
            can.Message(arbitration_id=PING_ID, is_extended_id=True, data=PAYLOAD.pack(token, STOP_COUNTER))
        )
        echo.wait(timeout=5)
    finally:
        bus.shutdown()
        if echo.poll() is None:
            echo.kill()
            echo.wait()
        echo.stdout.close()
    return result


# --------------------------------------------------------------------------- what the log says
def _us(values: np.ndarray[Any, Any], qs: tuple[float, ...] = (50, 99, 99.9)) -> dict[str, float] | None:
    if len(values) == 0:
        return None
    p = percentiles((values.astype(np.float64) / 1000).tolist(), qs)
    return {k: round(v, 1) for k, v in p.items()}


def skip_counts(data: LogData, planned: int | None = None) -> dict[str, int]:
    """Samples the ``feedback_lost``/``overrun_skip`` events announce, by kind.

    With ``planned``, only those inside the run (``first_sample + i < planned``): the runner fills
    no sample past the end, though an event near the end may count some.
    """
    out = dict.fromkeys(SKIP_EVENT_KINDS, 0)
    for e in data.events:
        if e.get("kind") in out:
            d = e.get("data", {})
            count = int(d.get("count", 0))
            if planned is not None:
                count = max(0, min(count, planned - int(d.get("first_sample", 0))))
            out[e["kind"]] += count
    return out


def timing_figures(data: LogData, period_ns: int) -> dict[str, Any]:
    """Overruns, feedback-to-command latency and receive lateness/jitter of a real-time log.

    - overrun samples: flagged overrun (flags bit 1; the runner found newer feedback queued and
      answered only the newest); skipped: samples whose feedback was never answered, from the
      ``overrun_skip`` and ``feedback_lost`` events. The goal counts both, as % of cycles.
    - late answers: answered samples whose command left after the next feedback's nominal
      instant (``tx_time_ns > time_ns + period_ns``), a direct check of "no command sent before
      the next feedback" that needs no flag.
    - latency: ``tx_time_ns - rx_time_ns`` over answered samples (link receive to command sent:
      decode, controller step, quantize, send, and the frame hooks of both frames).
    - lateness: ``rx_time_ns - time_ns`` (receive time against the nominal instant, which tracks
      the drive's clock); jitter: ``|rx interval - period|`` of consecutive answered samples.
    """
    s = data.samples
    n = len(s)
    flags = s["flags"]
    rx = s["rx_time_ns"].astype(np.int64)
    tx = s["tx_time_ns"].astype(np.int64)
    t = s["time_ns"].astype(np.int64)
    answered = (rx > 0) & (tx > 0)
    overrun_flagged = int(np.count_nonzero(flags & FLAG_OVERRUN))
    skips = skip_counts(data, n)
    skipped = sum(skips.values())
    missed = overrun_flagged + skipped
    late = int(np.count_nonzero(tx[answered] > t[answered] + period_ns))
    seq = s["seq"].astype(np.int64)
    pair = answered[1:] & answered[:-1] & (np.diff(seq) == 1)
    jitter = np.abs(np.diff(rx) - period_ns)[pair]
    return {
        "cycles": n,
        "answered": int(np.count_nonzero(answered)),
        "overrun_flagged": overrun_flagged,
        "skipped_overrun": skips["overrun_skip"],
        "skipped_lost": skips["feedback_lost"],
        "overrun_pct": 100.0 * missed / n if n else float("nan"),
        "late_answers": late,
        "late_answers_pct": 100.0 * late / n if n else float("nan"),
        "latency_us": _us(tx[answered] - rx[answered]),
        "lateness_us": _us(s["lateness_ns"][answered]),
        "jitter_us": _us(jitter),
        "compute_us": _us(s["compute_ns"][answered]),
    }


def kernel_to_command(data: LogData, node_id: int) -> dict[str, float] | None:
    """Socket receive (the kernel's SO_TIMESTAMPNS of the feedback frame) to the command's creation.

    From the frame channel: each COMMAND frame sent is paired with the last FEEDBACK frame
    received before it in the log (the one it answers); the difference of their timestamps
    (both wall clock) is what the latency from ``rx_time_ns`` leaves out on the receive side
    (select wake-up, recvmsg, msgpack unpack, Message) plus the rest up to the send, which
    itself is not included (its cost is ``udp_multicast_send_call_us``).
    """
    from dob_hil.link.protocol import FrameKind

    f = data.frames
    ident, direction = f["arbitration_id"], f["direction"]
    fb_rows = np.nonzero((direction == 0) & (ident == FrameKind.FEEDBACK + node_id))[0]
    cmd_rows = np.nonzero((direction == 1) & (ident == FrameKind.COMMAND + node_id))[0]
    pos = np.searchsorted(fb_rows, cmd_rows) - 1
    keep = pos >= 0
    keep[1:] &= pos[1:] != pos[:-1]  # one command per feedback: the first that followed it
    ts = f["timestamp_ns"].astype(np.int64)
    return _us(ts[cmd_rows[keep]] - ts[fb_rows[pos[keep]]])


def accounting(data: LogData, planned: int) -> dict[str, Any]:
    """Whether every sample was recorded: seq 0..planned-1 without gaps, fills all explained.

    ``event_counts_past_the_end``: samples that skip events announce beyond the last planned
    sample (the runner counts them in the event, fills none): reported, not held against the log.
    """
    s = data.samples
    seq = s["seq"].astype(np.int64)
    gaps = int(np.sum(np.maximum(np.diff(seq) - 1, 0))) if len(seq) > 1 else 0
    in_order = bool(len(seq) == 0 or (seq[0] == 0 and np.all(np.diff(seq) == 1)))
    missing = int(np.count_nonzero(s["flags"] & FLAG_FEEDBACK_MISSING))
    announced = sum(skip_counts(data).values())
    explained = sum(skip_counts(data, planned).values())
    dropped_text = data.metadata.get("summary", {}).get("dropped_records")
    dropped = int(dropped_text) if dropped_text is not None else None
    return {
        "samples": len(s),
        "planned": planned,
        "seq_gaps": gaps,
        "seq_contiguous_from_0": in_order,
        "flagged_missing": missing,
        "explained_by_events": explained,
        "event_counts_past_the_end": announced - explained,
        "log_complete": data.complete,
        "log_dropped_records": dropped,
        "log_warnings": data.warnings[:5],
        "all_recorded": bool(
            len(s) == planned and in_order and missing == explained and data.complete and dropped == 0
        ),
    }
