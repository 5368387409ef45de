"""Lockstep full stack vs a bare two-frame exchange on python-can's virtual bus, in the same run.

Full stack: the profile's simulated drive + the lockstep bus + the profile's link + controller +
MCAP logging of samples, frames and ground truth (``run_session`` on a shipped scenario), on the
default in-process bus (``RunOptions.bus_impl = "inprocess"``: python-can ``BusABC``, no copies),
for every profile: native (``paper-step``), CiA 402 (``paper-step-cia402``: SYNC, RxPDO, TxPDO
per sample) and ODrive (``paper-step-odrive``). The native stack is also timed on python-can's
``virtual`` for comparison. Baseline: one thread sends a 6-byte frame on one end of a python-can
virtual bus, receives it on the other end, answers with a 3-byte frame and receives that: the two
frames of a cycle and nothing else. Every repeat times the baseline and each stack back to back
(same machine state); the ratios are taken per repeat. Goal (issue 16): every profile's full
stack with logging at least as fast as the bare exchange (ratio <= 1.0), on wall time. Beside it,
the loop thread's CPU time per sample (``*_cpu_ratio``: marginal CPU of the session against the
bare exchange's CPU), which a loaded machine disturbs less: waiting for a CPU is not counted.

    .venv/bin/python benchmarks/bench_lockstep.py [--smoke] [--json] [--repeats N] [--samples N]
"""

from __future__ import annotations

import tempfile
import time
import uuid
from pathlib import Path

import can
from _common import median, parser, report

from dob_hil.config import load_config
from dob_hil.loop.session import RunOptions, run_session
from dob_hil.scenarios import scenario_path

PROFILES = {"native": "paper-step", "cia402": "paper-step-cia402", "odrive": "paper-step-odrive"}


def bare_exchange(n: int) -> tuple[float, float]:
    """(wall us, CPU us of this thread) per exchange."""
    channel = f"bench-{uuid.uuid4().hex}"
    host = can.Bus(interface="virtual", channel=channel)
    drive = can.Bus(interface="virtual", channel=channel)
    try:
        fb = bytes(6)
        cmd = bytes(3)
        t0 = time.perf_counter_ns()
        c0 = time.thread_time_ns()
        for _ in range(n):
            drive.send(can.Message(arbitration_id=0x181, data=fb, is_extended_id=False))
            host.recv(0.0)
            host.send(can.Message(arbitration_id=0x201, data=cmd, is_extended_id=False))
            drive.recv(0.0)
        cpu = time.thread_time_ns() - c0
        return (time.perf_counter_ns() - t0) / n / 1000.0, cpu / n / 1000.0
    finally:
        host.shutdown()
        drive.shutdown()


# The frames of one period of each profile, in order: (sent by the host?, id, data length, remote).
PROFILE_FRAMES: dict[str, tuple[tuple[bool, int, int, bool], ...]] = {
    "native": ((False, 0x6B1, 6, False), (True, 0x6A1, 3, False)),
    "cia402": ((True, 0x80, 0, False), (False, 0x181, 6, False), (True, 0x201, 4, False)),
    "odrive": ((True, 0x29, 8, True), (False, 0x29, 8, False), (True, 0x2E, 8, False)),
}


def bare_profile_exchange(n: int, frames: tuple[tuple[bool, int, int, bool], ...]) -> float:
    """CPU us of this thread per period for a bare exchange of a profile's own frames on ``virtual``.

    Each frame is a fresh ``can.Message`` sent on one end and received on the other, as in
    :func:`bare_exchange`; a profile with three frames per period (CiA 402: SYNC, RxPDO, TxPDO;
    ODrive: the RTR, its answer, the torque) is compared with three.
    """
    channel = f"bench-{uuid.uuid4().hex}"
    host = can.Bus(interface="virtual", channel=channel)
    drive = can.Bus(interface="virtual", channel=channel)
    try:
        plan = [(host if by_host else drive, drive if by_host else host, aid, bytes(dlc), remote)
                for by_host, aid, dlc, remote in frames]  # fmt: skip
        c0 = time.thread_time_ns()
        for _ in range(n):
            for sender, receiver, aid, data, remote in plan:
                dlc = 8 if remote else len(data)
                msg = can.Message(
                    arbitration_id=aid, data=data, is_extended_id=False, is_remote_frame=remote, dlc=dlc
                )
                sender.send(msg)
                receiver.recv(0.0)
        return (time.thread_time_ns() - c0) / n / 1000.0
    finally:
        host.shutdown()
        drive.shutdown()


def bare_exchange_us(n: int) -> float:
    return bare_exchange(n)[0]


def _session(
    scenario: str, n_samples: int, tmp: Path, tag: str, bus_impl: str
) -> tuple[float, int, int, int]:
    """(wall us per sample, samples, CPU ns of this thread for the whole session, dropped records)."""
    config = load_config(scenario_path(scenario))
    path = tmp / f"lockstep-{scenario}-{bus_impl}-{tag}.mcap"
    duration_s = n_samples * config.plant.period_ns * 1e-9
    c0 = time.thread_time_ns()
    summary = run_session(config, RunOptions(duration_s=duration_s, log_path=path, bus_impl=bus_impl))
    cpu_ns = time.thread_time_ns() - c0
    path.unlink()
    wall_us = summary.wall_time_s / summary.samples * 1e6
    return wall_us, summary.samples, cpu_ns, summary.log_dropped_records


def full_stack_us(scenario: str, n_samples: int, tmp: Path, tag: str, bus_impl: str) -> tuple[float, int]:
    wall_us, _, _, dropped = _session(scenario, n_samples, tmp, tag, bus_impl)
    return wall_us, dropped


def full_stack(
    scenario: str, n_samples: int, tmp: Path, tag: str, bus_impl: str
) -> tuple[float, float, float, int]:
    """(wall us per sample, marginal wall us per sample, marginal CPU us per sample, dropped records).

    The marginal figures are those of the run minus those of a run of a tenth of the samples, per
    extra sample: the fixed cost of a run (the enable sequence, e.g. CiA 402's SDO configuration
    over canopen, inside the loop's wall time) cancels out. The CPU figure is this thread's CPU
    time: time spent waiting for a CPU (the machine's other load, the writer process) is not
    counted either.
    """
    short = max(1, n_samples // 10)
    wall_short, n_short, cpu_short, drop_short = _session(scenario, short, tmp, tag + "s", bus_impl)
    wall_us, n_long, cpu_long, dropped = _session(scenario, n_samples, tmp, tag, bus_impl)
    extra = n_long - n_short
    marginal_wall_us = (wall_us * n_long - wall_short * n_short) / extra
    return wall_us, marginal_wall_us, (cpu_long - cpu_short) / extra / 1000.0, dropped + drop_short


def main() -> None:
    p = parser(__doc__ or "")
    p.add_argument("--repeats", type=int, default=None, help="repeats (default 7; --smoke 1)")
    p.add_argument("--samples", type=int, default=None, help="samples per run (default 33,333; smoke 1,000)")
    args = p.parse_args()
    repeats = args.repeats or (1 if args.smoke else 7)
    n_samples = args.samples or (1_000 if args.smoke else 33_333)
    n_bare = 2_000 if args.smoke else 50_000
    bare: list[float] = []
    bare_cpu: list[float] = []
    full: dict[str, list[float]] = {name: [] for name in PROFILES}
    full_cpu: dict[str, list[float]] = {name: [] for name in PROFILES}
    full_marginal: dict[str, list[float]] = {name: [] for name in PROFILES}
    virtual: list[float] = []
    bare_own: dict[str, list[float]] = {name: [] for name in PROFILES}
    dropped = 0
    with tempfile.TemporaryDirectory() as d:
        for i in range(repeats):  # interleaved, so all see the same machine state
            wall, cpu = bare_exchange(n_bare)
            bare.append(wall)
            bare_cpu.append(cpu)
            for name, scenario in PROFILES.items():
                bare_own[name].append(bare_profile_exchange(n_bare, PROFILE_FRAMES[name]))
                us, marginal_us, cpu_us, drop = full_stack(scenario, n_samples, Path(d), str(i), "inprocess")
                full[name].append(us)
                full_marginal[name].append(marginal_us)
                full_cpu[name].append(cpu_us)
                dropped += drop
            us_v, drop_v = full_stack_us(PROFILES["native"], n_samples, Path(d), str(i), "virtual")
            virtual.append(us_v)
            dropped += drop_v
    bare_us = median(bare)
    result: dict[str, object] = {
        "repeats": repeats,
        "samples_per_run": n_samples,
        "bare_exchange_us": {"median": bare_us, "min": min(bare), "max": max(bare)},
        "bare_exchange_cpu_us": {"median": median(bare_cpu), "min": min(bare_cpu), "max": max(bare_cpu)},
    }
    worst = 0.0
    for name, values in full.items():
        ratios = [f / b for f, b in zip(values, bare, strict=True)]  # per repeat: same machine state
        cpu_ratios = [f / b for f, b in zip(full_cpu[name], bare_cpu, strict=True)]
        worst = max(worst, median(ratios))
        result[f"{name}_full_stack_us_per_sample"] = {
            "median": median(values), "min": min(values), "max": max(values)
        }  # fmt: skip
        result[f"{name}_ratio_full_over_bare"] = {
            "median": median(ratios), "min": min(ratios), "max": max(ratios)
        }  # fmt: skip
        marginal_ratios = [f / b for f, b in zip(full_marginal[name], bare, strict=True)]
        result[f"{name}_marginal_wall_us_per_sample"] = median(full_marginal[name])
        result[f"{name}_marginal_wall_ratio"] = {
            "median": median(marginal_ratios), "min": min(marginal_ratios), "max": max(marginal_ratios)
        }  # fmt: skip
        result[f"{name}_cpu_us_per_sample"] = median(full_cpu[name])
        result[f"{name}_cpu_ratio"] = {
            "median": median(cpu_ratios),
            "min": min(cpu_ratios),
            "max": max(cpu_ratios),
        }
        own_ratios = [f / b for f, b in zip(full_cpu[name], bare_own[name], strict=True)]
        result[f"{name}_bare_own_frames_cpu_us"] = median(bare_own[name])
        result[f"{name}_cpu_ratio_vs_own_frames"] = {
            "median": median(own_ratios), "min": min(own_ratios), "max": max(own_ratios)
        }  # fmt: skip
    v_ratios = [f / b for f, b in zip(virtual, bare, strict=True)]
    result["native_on_virtual_us_per_sample"] = {"median": median(virtual), "ratio": median(v_ratios)}
    result["log_dropped_records"] = dropped
    result["goal"] = "ratio full/bare <= 1.0 on every profile"
    result["goal_met"] = worst <= 1.0
    report("lockstep full stack vs bare virtual-bus exchange", result, args.json)


if __name__ == "__main__":
    main()
