"""The standalone simulated drive: ``python -m firmware_sim CONFIG [bus options] [--duration S]``.

Runs the drive on its real-time clock on any python-can bus until SIGINT/SIGTERM or
``--duration`` seconds. Exit status 0 on a clean stop (a signal is a clean stop; a second one
during the stop ends it at once), 2 with one line on stderr for a bad config or bad arguments,
1 with one line for a bus that cannot be opened or a drive thread that failed. A frame the bus
cannot deliver (a stray datagram on the udp_multicast port) is counted, not fatal; a diverging
plant is a FAULT (ENCODER), not a crash.

Spinning: by default (``--spin-us auto``) the drive busy-waits the last 100 us before each
deadline only when it runs under SCHED_FIFO pinned to CPUs of its own (``--sched-fifo --cpu N``,
both granted), and sleeps otherwise: on a shared CPU a spin takes time another process needs.
Even then the spin yields the CPU on every turn.
"""

from __future__ import annotations

import argparse
import gc
import signal
import sys
import threading
import time
from collections.abc import Sequence
from types import FrameType
from typing import Any

import can

from dob_hil.config import Config, load_config
from dob_hil.errors import ConfigError, DobHilError
from dob_hil.link.axes import axis_node_ids, check_square
from dob_hil.loop.blas import one_blas_thread
from dob_hil.loop.rt_os import RtSettings, apply_rt_settings
from firmware_sim.axes import MultiAxisDrive, make_simulated_drive
from firmware_sim.behaviour import VARIANTS
from firmware_sim.cia402 import SimulatedCia402Drive
from firmware_sim.drive import SimulatedDrive
from firmware_sim.odrive import SimulatedOdrive
from firmware_sim.plant import check_single_axis
from firmware_sim.process import READY_TEXT
from firmware_sim.truth import UdpTruthSender

PROG = "firmware_sim"
AUTO_SPIN_US = 100.0  # --spin-us auto, under SCHED_FIFO on CPUs of its own


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=f"python -m {PROG}",
        description="Simulated servo drive (native dob_hil CAN protocol) on its own real-time clock.",
    )
    p.add_argument("config", help="TOML config (plant, drive and sim sections are used)")
    p.add_argument("-i", "--interface", help="python-can interface (socketcan, udp_multicast, virtual, ...)")
    p.add_argument("-c", "--channel", help="python-can channel (vcan0, 239.74.163.2, ...)")
    p.add_argument("-b", "--bitrate", type=int, help="bus bitrate in bit/s")
    p.add_argument("--duration", type=float, help="stop after this many seconds (default: until a signal)")
    p.add_argument("--truth-port", type=int, help="send ground truth as UDP datagrams to 127.0.0.1:PORT")
    p.add_argument(
        "--sched-fifo",
        action="store_true",
        help="run the drive's threads under SCHED_FIFO (where permitted), like firmware on its own core",
    )
    p.add_argument("--cpu", type=int, action="append", help="pin the drive to this CPU (repeatable)")
    p.add_argument(
        "--spin-us",
        default="auto",
        help=f"busy-wait (yielding) this long before each deadline for timing precision; 0 = sleep only; "
        f"default auto: {AUTO_SPIN_US:g} under --sched-fifo with --cpu (both granted), else 0",
    )
    p.add_argument(
        "--watchdog-periods",
        type=int,
        help="override drive.watchdog_periods: periods without a valid command before a WATCHDOG fault",
    )
    p.add_argument(
        "--variant",
        choices=sorted(VARIANTS),
        default="reference",
        help="drive behaviour: a variant PROTOCOL.md permits or a deliberate violation "
        "(for testing hosts and the conformance kit; default reference)",
    )
    return p


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    args = build_parser().parse_args(argv)
    if args.duration is not None and not args.duration > 0:
        build_parser().error(f"--duration must be > 0, got {args.duration}")
    if args.truth_port is not None and not 1 <= args.truth_port <= 65535:
        build_parser().error(f"--truth-port must be 1..65535, got {args.truth_port}")
    if args.spin_us != "auto":
        try:
            args.spin_us = float(args.spin_us)
        except ValueError:
            build_parser().error(f"--spin-us must be a number of microseconds or auto, got {args.spin_us!r}")
        if not 0 <= args.spin_us < 1e6:
            build_parser().error(f"--spin-us must be 0..999999, got {args.spin_us}")
    if args.watchdog_periods is not None and not 1 <= args.watchdog_periods <= 1_000_000:
        build_parser().error(f"--watchdog-periods must be 1..1000000, got {args.watchdog_periods}")
    return args


def _with_overrides(config: Config, args: argparse.Namespace) -> Config:
    if args.watchdog_periods is None:
        return config
    import dataclasses

    drive = dataclasses.replace(config.drive, watchdog_periods=args.watchdog_periods)
    return dataclasses.replace(config, drive=drive)


def _variant_text(variant: str) -> str:
    return "" if variant == "reference" else f", variant {variant}"


def _spin_ns(args: argparse.Namespace, applied: list[str]) -> int:
    """--spin-us in ns; auto: spin only under SCHED_FIFO on CPUs of its own, both granted."""
    if args.spin_us != "auto":
        return round(float(args.spin_us) * 1000)
    fifo = any(a.startswith("SCHED_FIFO") for a in applied)
    pinned = any(a.startswith("CPU affinity") for a in applied)
    return round(AUTO_SPIN_US * 1000) if fifo and pinned and args.cpu else 0


def _fail(status: int, message: str) -> int:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    return status


def main(argv: Sequence[str] | None = None) -> int:
    """The drive process; BLAS on one thread (:mod:`dob_hil.loop.blas`: no spinning workers
    beside the drive's threads)."""
    with one_blas_thread():
        return _main(argv)


def _main(argv: Sequence[str] | None) -> int:
    args = parse_args(argv)
    try:
        config = _with_overrides(load_config(args.config), args)
        bus_kwargs: dict[str, Any] = {}
        for key in ("interface", "channel", "bitrate"):
            if getattr(args, key) is not None:
                bus_kwargs[key] = getattr(args, key)
        if config.drive.profile == "native" and config.plant.n_inputs > 1:  # several axes on one bus
            nodes = axis_node_ids(config.drive, check_square(config.plant))  # refused before the bus
        else:
            check_single_axis(config.plant)  # refuse the plant before opening a bus
            nodes = (config.drive.node_id,)
    except DobHilError as exc:
        return _fail(2, str(exc))
    try:
        bus = can.Bus(**bus_kwargs)
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as exc:
        return _fail(1, f"cannot open the bus ({bus_kwargs or 'python-can defaults'}): {exc}")

    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        if stop.is_set():  # a second signal while stopping: stop at once
            raise KeyboardInterrupt
        stop.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    sink = UdpTruthSender(args.truth_port) if args.truth_port is not None else None
    status = 0
    try:
        gc.freeze()  # long-lived objects out of the collector's way (gen-2 pauses of several ms)
        # OS plumbing only (no controller code): the drive's threads inherit these settings
        rt = apply_rt_settings(RtSettings(sched_fifo=args.sched_fifo, cpus=tuple(args.cpu or ())))
        for refused in rt.refused:
            print(f"{PROG}: warning: {refused}", file=sys.stderr, flush=True)
        spin_ns = _spin_ns(args, rt.applied)
        drive: SimulatedDrive | MultiAxisDrive | SimulatedCia402Drive | SimulatedOdrive
        try:
            if config.drive.profile == "cia402":  # the host's SYNC is this drive's clock: no timer to spin
                drive = SimulatedCia402Drive(bus, config, clock="realtime", truth_sink=sink)
            elif config.drive.profile == "odrive":  # the simulated ODrive (CANSimple)
                drive = SimulatedOdrive(bus, config, clock="realtime", truth_sink=sink, spin_ns=spin_ns)
            else:  # one node, or one per axis of a multi-input plant
                drive = make_simulated_drive(
                    bus,
                    config,
                    clock="realtime",
                    truth_sink=sink,
                    spin_ns=spin_ns,
                    behaviour=VARIANTS[args.variant],
                )
        except (ValueError, ArithmeticError) as exc:  # a config value the simulation cannot hold
            raise ConfigError("config", f"{args.config}: the simulated drive cannot run it: {exc}") from None
        drive.start()
        print(
            f"{PROG}: {'nodes' if len(nodes) > 1 else 'node'} {', '.join(map(str, nodes))} "
            f"on {bus.channel_info}, "
            f"period {config.plant.period_ns / 1000:g} us, watchdog {config.drive.watchdog_periods} periods, "
            f"spin {spin_ns / 1000:g} us{_variant_text(args.variant)}; {READY_TEXT}",
            file=sys.stderr,
            flush=True,
        )
        try:
            end_s = None if args.duration is None else time.monotonic() + args.duration
            while not stop.is_set():
                wait_s = 0.1 if end_s is None else min(0.1, end_s - time.monotonic())
                if wait_s <= 0 or stop.wait(wait_s):
                    break
                drive.check()
        finally:
            drive.close()
        if isinstance(drive, SimulatedCia402Drive):
            print(f"{PROG}: stopped: {drive.stats}", file=sys.stderr)
        else:
            stats = drive.stats
            if isinstance(drive, MultiAxisDrive):  # per-node firmware counters, summed
                per_axis = drive.axis_stats
                stats.samples = per_axis[0].samples
                stats.commands_accepted = sum(a.commands_accepted for a in per_axis)
            print(
                f"{PROG}: stopped after {stats.samples} samples "
                f"({stats.feedback_sent} feedback sent, {stats.feedback_lost} lost, "
                f"{stats.commands_accepted} commands, {stats.overruns} overruns, "
                f"{stats.rx_errors} undeliverable frames, final state {drive.state.name})",
                file=sys.stderr,
            )
    except DobHilError as exc:
        status = _fail(2, str(exc))
    except KeyboardInterrupt:
        status = _fail(130, "stopped by a second signal while stopping")
    except Exception as exc:
        status = _fail(1, f"drive stopped: {type(exc).__name__}: {exc}")
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)
        if sink is not None:
            sink.close()
        bus.shutdown()
    return status
