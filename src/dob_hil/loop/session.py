"""One run, from a config to a finalised log: build, enable, loop, and always stop safely.

Whatever ends the run (completion, a drive fault, a host timeout, a safety-envelope trip, an
exception, SIGINT or SIGTERM), the ``finally`` path commands zero current, disables the drive and
finalises the log with a summary naming the exit reason. The signal handlers stay installed until
the log is closed: a second SIGINT or SIGTERM while stopping is noted, not fatal.
"""

from __future__ import annotations

import functools
import itertools
import json
import os
import signal
import sys
import time
import types
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, cast

import can

from dob_hil.config import Config
from dob_hil.control.reference import make_reference
from dob_hil.control.step import Gains, compile_step
from dob_hil.design import Design, build_design
from dob_hil.design.tracking import tracking_map
from dob_hil.errors import DobHilError, DriveFault
from dob_hil.link.base import LinkEvent
from dob_hil.link.bus import open_bus
from dob_hil.link.busload import refuse_overload
from dob_hil.log import LogLayout, LogWriter, run_metadata, versions_metadata
from dob_hil.log.writer import message_flags
from dob_hil.loop.blas import one_blas_thread
from dob_hil.loop.cycle import ControlCycle, CycleStats
from dob_hil.loop.envelope import Envelope, SafetyTrip, check_encoder_resolution, encoder_jump_speed
from dob_hil.loop.heap import frozen_heap
from dob_hil.loop.host_clocked import HostClockedLink, run_host_clocked_lockstep, run_host_clocked_realtime
from dob_hil.loop.inproc_bus import BUS_IMPLS, bus_pair
from dob_hil.loop.rt_os import RtSettings, apply_rt_settings, restore_rt_settings
from dob_hil.loop.runners import LoopLimits, run_lockstep, run_realtime
from dob_hil.loop.timeline import LoopLog, frame_clamp
from dob_hil.profiles import Clocking, DriveProfile, SimulatedCounterpart, get_profile

_channel_counter = itertools.count()
EMBEDDED_RT_SWITCH_INTERVAL_S = 100e-6
EMBEDDED_RT_STOP_GRACE_S = 1.0  # the embedded real-time drive's time to act on the stop sequence


@dataclass(frozen=True)
class RunOptions:
    interface: str | None = None
    channel: str | None = None
    bitrate: int | None = None
    dob_enabled: bool | None = None  # None: the config's run.dob_enabled
    duration_s: float | None = None  # None: the config's run.duration_s
    log_path: Path | None = None
    realtime: bool = False  # real time even with the embedded drive
    rt: RtSettings = field(default_factory=RtSettings)
    progress: Callable[[int, int], None] | None = None  # (done, total)
    enable_timeout_s: float = 2.0
    # wraps the host's bus end (fault injection in tests: firmware_sim.faulty_bus.FaultyBus)
    bus_wrapper: Callable[[can.BusABC], can.BusABC] | None = None
    # the embedded lockstep bus: "inprocess" (no copies) or python-can's "virtual"
    bus_impl: str = "inprocess"
    log_layout: str | None = None  # None: the config's run.log_layout ("samples" or "blocks")
    # the simulated drive's plant ("truth"), when it differs from the design's (campaigns)
    sim_config: Config | None = None
    live: Any = None  # dob_hil.live.process.LiveOptions: serve the run to Foxglove (--live)


@dataclass
class RunSummary:
    name: str
    log_path: str
    mode: str
    dob_enabled: bool
    exit_reason: str
    samples: int
    planned_samples: int
    duration_s: float
    wall_time_s: float
    samples_per_s: float
    saturated_samples: int
    missing_samples: int
    skipped_samples: int
    overruns: int
    max_abs_current_A: float
    unsequenced_periods: int  # periods a stall hid from the sequence number, counted by time
    current_limit_A: float
    compute_ns_max: int
    log_dropped_records: int
    events: dict[str, int]
    rt_applied: list[str]
    rt_refused: list[str]
    live: dict[str, int] | None = None  # --live: items forwarded/dropped, port

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class _StopFlag:
    """Set by SIGINT/SIGTERM or a safety-envelope trip; the loop checks it every sample. A second
    SIGINT while the loop runs raises at once (a loop stuck somewhere); once stopping, further
    signals are only counted, so that the stop sequence and the log's close always finish."""

    def __init__(self) -> None:
        self.requested: str | None = None
        self.stopping = False
        self.ignored_signals = 0

    def trip(self, reason: str) -> None:
        if self.requested is None:
            self.requested = reason

    def handler(self, signum: int, frame: types.FrameType | None) -> None:
        name = signal.Signals(signum).name
        if self.stopping:
            self.ignored_signals += 1
            return
        if self.requested is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.trip(name)


@contextmanager
def _signals(flag: _StopFlag) -> Iterator[None]:
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.signal(s, flag.handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _frame_stamper(
    log: LogWriter, lockstep_drive: Any, loop_log: LoopLog
) -> Callable[[can.Message, bool], None]:
    """Log frames on the samples' clock, so that frames and samples line up (in Foxglove too).

    Lockstep: the simulated drive's time (the sample instants are ``k * period_ns`` of it). Real
    time: the bus timestamp (python-can's ``time.time()`` base for most interfaces) moved onto
    ``time.monotonic_ns`` by the offset between the two clocks taken at the start, kept
    non-decreasing; the hook only queues the frame with its time, and the control thread packs
    it at its next flush, after the command is sent (``LoopLog.defer_frames``).
    """
    frame_raw = log.frame_raw

    def parts(msg: can.Message) -> tuple[int, int, bytes | bytearray, int]:
        return msg.arbitration_id, msg.dlc, msg.data or b"", message_flags(msg)

    if lockstep_drive is not None:
        # the drive's time without its property chain, where the simulated drive offers it
        source_of = getattr(lockstep_drive, "lockstep_time_source", None)
        return log.clocked_frame_hook(source_of() if source_of is not None else lockstep_drive)
    offset_ns = time.monotonic_ns() - time.time_ns()
    clamp = frame_clamp()  # non-decreasing: an own echo's bus time can precede the send's log time
    pending: list[tuple[int, can.Message, bool]] = []
    monotonic_ns = time.monotonic_ns

    def stamp_realtime(msg: can.Message, is_rx: bool) -> None:
        # only the clock reading that cannot wait (no bus timestamp); the rest at the flush
        pending.append((0 if msg.timestamp else monotonic_ns(), msg, is_rx))

    def write_pending() -> None:
        for t, msg, is_rx in pending:
            aid, dlc, data, flags = parts(msg)
            ts = msg.timestamp
            frame_raw(clamp(round(ts * 1e9) + offset_ns if ts else t), aid, is_rx, dlc, data, flags)
        pending.clear()

    loop_log.defer_frames(pending, write_pending)
    return stamp_realtime


def _truth_sink(log: LogWriter) -> Callable[[Any], None]:
    """The simulated drive's ground truth to the log (one call per period: the writer's hook)."""
    return log.truth_hook()


def default_log_path(config: Config, dob_enabled: bool) -> Path:
    stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S-%f")
    return config.run.log_dir / f"{config.name}-{'dob' if dob_enabled else 'nodob'}-{stamp}.mcap"


def run_session(config: Config, options: RunOptions) -> RunSummary:
    """Run one session; raises DobHilError subclasses for bad input, after stopping safely.

    BLAS runs on one thread throughout (:mod:`dob_hil.loop.blas`): no spinning workers beside
    the loop."""
    with one_blas_thread():
        return _run_session(config, options)


def _run_session(config: Config, options: RunOptions) -> RunSummary:
    dob_enabled = config.run.dob_enabled if options.dob_enabled is None else options.dob_enabled
    design = build_design(config, dob_enabled=dob_enabled)
    profile = get_profile(config.drive.profile)
    profile.check_period(config.plant.period_ns)
    profile.check_axes(config)  # before any bus opens: a real drive is never enabled for it
    refuse_overload(profile.bus_load(config))
    duration_s = options.duration_s if options.duration_s is not None else config.run.duration_s
    if not duration_s > 0:
        raise DobHilError(f"--duration: must be > 0 s, got {duration_s}")
    if options.bus_impl not in BUS_IMPLS:
        raise DobHilError(f"--bus-impl: expected one of {', '.join(BUS_IMPLS)}, got {options.bus_impl!r}")
    check_encoder_resolution(config, duration_s)
    period_ns = config.plant.period_ns
    n_samples = max(1, round(duration_s * 1e9 / period_ns))
    tracking = tracking_map(design)  # x_ref = Nx r + Nv r', u_ref = Kff x_ref (any plant)
    gains = Gains(design.Phi, design.Gam, design.C, design.Lc, design.Kc, design.Kdist, Kff=tracking.Kff)
    step = compile_step(gains, dob_enabled)
    reference = make_reference(
        config.reference, step.n_states, config.plant.period_s, state_map=(tracking.Nx, tracking.Nv)
    )
    external_bus = options.interface is not None or options.channel is not None
    mode = "realtime" if (external_bus or options.realtime) else "lockstep"
    log_path = options.log_path or default_log_path(config, dob_enabled)
    log_path.parent.mkdir(parents=True, exist_ok=True)
    layout = LogLayout(
        n_states=step.n_states,
        n_inputs=step.n_inputs,
        n_outputs=step.n_outputs,
        n_plant_states=config.plant.n_states,
    )
    bus = "virtual (embedded firmware_sim)" if not external_bus else f"{options.interface or 'default'}"
    run_meta = run_metadata(
        mode=mode,
        bus=bus,
        period_ns=period_ns,
        layout=layout,
        channel=str(options.channel or ""),
        bitrate_bps=str(options.bitrate or config.drive.bitrate_bps),
        planned_samples=str(n_samples),
        dob_enabled=str(dob_enabled).lower(),
        scenario=config.name,
        current_limit_A=repr(config.drive.current_limit_A),
        dac_lsb_A=repr(config.drive.dac_lsb_A),
        encoder_counts_per_unit=repr(config.drive.encoder_counts_per_unit),
        missing_feedback_policy=config.run.missing_feedback_policy,
    )
    design_json = design.to_json()
    flag = _StopFlag()
    writer: Callable[..., LogWriter] = LogWriter
    live_ctx: AbstractContextManager[Any] = nullcontext()
    live = None
    if options.live is not None:  # before the drive is enabled: a port that cannot serve stops here
        from dob_hil.live.process import LiveServer
        from dob_hil.live.tap import TappedLogWriter

        live_ctx = live = LiveServer(options.live, layout, period_ns, design_json, run_meta)
        writer = functools.partial(TappedLogWriter, tap=live.tap)
    with (
        _signals(flag),
        live_ctx,
        writer(
            log_path,
            layout,
            metadata={"run": run_meta, "versions": versions_metadata()},
            attachments={"design.json": design_json.encode(), "config.toml": config.text.encode()},
            backpressure=mode == "lockstep",  # real time drops (counted) rather than wait
            message_layout=options.log_layout or config.run.log_layout,
        ) as log,
    ):
        summary = _run_with_log(config, profile, options, design, step, reference, log, log_path, mode,
                                n_samples, dob_enabled, external_bus, flag)  # fmt: skip
    if live is not None:
        summary.live = {**live.tap.stats.as_dict(), "port": live.port}
    return summary


def _rt_settings(config: Config, options: RunOptions) -> RtSettings:
    """``[run] sched_fifo``, ``cpu_affinity``, ``freeze_gc``, overridden by the command line's."""
    rt, run = options.rt, config.run
    return RtSettings(
        sched_fifo=rt.sched_fifo or run.sched_fifo,
        fifo_priority=rt.fifo_priority,
        cpus=rt.cpus if rt.cpus else run.cpu_affinity,
        freeze_gc=rt.freeze_gc or run.freeze_gc,
    )


def _run_with_log(
    config: Config,
    profile: DriveProfile,
    options: RunOptions,
    design: Design,
    step: Any,
    reference: Any,
    log: LogWriter,
    log_path: Path,
    mode: str,
    n_samples: int,
    dob_enabled: bool,
    external_bus: bool,
    flag: _StopFlag,
) -> RunSummary:
    event_counts: dict[str, int] = {}
    drive_bus: can.BusABC | None = None
    drive: SimulatedCounterpart | None = None
    loop_log = LoopLog(log, None)
    if external_bus:
        host_bus = open_bus(options.interface, options.channel, options.bitrate)
    else:
        channel = f"dob-hil-{os.getpid()}-{next(_channel_counter)}"
        # lockstep: one thread, a bus without copies; the embedded real-time drive has threads
        host_bus, drive_bus = bus_pair(channel, options.bus_impl if mode == "lockstep" else "virtual")
        sink = _truth_sink(log) if mode == "lockstep" else loop_log.queue_truth
        sim_config = options.sim_config or config
        try:
            drive = profile.make_sim(
                drive_bus, sim_config, "realtime" if options.realtime else "lockstep", sink
            )
        except BaseException:  # a config the simulated drive refuses: release both ends first
            host_bus.shutdown()
            drive_bus.shutdown()
            raise
        if mode == "lockstep":
            sim = drive

            def sim_time_ns() -> int:
                return sim.time_ns

            loop_log = LoopLog(log, sim_time_ns)  # every channel on the simulated clock
    envelope = Envelope(
        config.safety,
        C_rows=tuple(tuple(float(c) for c in row) for row in design.C),
        period_ns=config.plant.period_ns,
        default_max_velocity=encoder_jump_speed(config),
        trip=flag.trip,
    )

    def on_event(ev: LinkEvent) -> None:
        kind = ev.kind.value
        event_counts[kind] = event_counts.get(kind, 0) + 1
        level = "error" if kind in ("drive_fault", "send_failed") else "warning"
        if kind == "drive_state":
            level = "info"
        loop_log.event(ev.time_ns, level, kind, ev.message)
        if kind == "encoder_jump":
            envelope.encoder_jump()

    frame_hook = _frame_stamper(log, drive if mode == "lockstep" else None, loop_log)
    if options.bus_wrapper is not None:
        host_bus = options.bus_wrapper(host_bus)
    link = profile.make_link(host_bus, config, frame_hook, on_event)
    cycle = ControlCycle(
        step,
        reference,
        link,
        log,
        dob_enabled=dob_enabled,
        missing_policy=config.run.missing_feedback_policy,
        max_missing_periods=config.run.max_missing_periods,
        C_rows=tuple(tuple(float(c) for c in row) for row in design.C),
        sim_time=mode == "lockstep",
        check=envelope.check,
    )
    limits = LoopLimits(n_samples, config.plant.period_ns, config.drive.feedback_timeout_periods)
    rt = _rt_settings(config, options)
    rt_report = apply_rt_settings(rt) if mode == "realtime" else None
    if rt_report is not None:
        for msg in rt_report.refused:
            loop_log.event(None, "warning", "rt_setting_refused", msg)
            print(f"dob-hil run: warning: {msg}", file=sys.stderr)
    progress = None
    if options.progress is not None:
        report = options.progress

        def progress(k: int) -> None:
            report(k, n_samples)

    exit_reason = "error"
    switch_interval_s = sys.getswitchinterval()
    t_start = time.perf_counter()
    try:
        loop_log.event(None, "info", "run_start", f"{mode} run of {n_samples} samples")
        runner: Callable[[], str]
        # a host-clocked profile's link requests every answer (HostClockedLink)
        host_link = cast(HostClockedLink, link) if profile.clocking is Clocking.HOST else None
        if mode == "lockstep":
            assert drive is not None
            link.enable_lockstep(drive.service)
            if host_link is not None:
                runner = functools.partial(
                    run_host_clocked_lockstep, cycle, host_link, drive, loop_log, limits, flag, progress
                )
            else:
                runner = functools.partial(run_lockstep, cycle, link, drive, loop_log, limits, flag, progress)
        else:
            if drive is not None:
                # the embedded drive's threads share this process's GIL with the loop: hand
                # it over every 100 us instead of 5 ms (timing stays indicative only; a drive
                # in its own process is the real-time setup)
                sys.setswitchinterval(EMBEDDED_RT_SWITCH_INTERVAL_S)
                drive.start()
            link.enable(int(options.enable_timeout_s * 1e9))
            if host_link is not None:
                runner = functools.partial(
                    run_host_clocked_realtime, cycle, host_link, loop_log, limits, flag, progress=progress
                )
            else:
                runner = functools.partial(
                    run_realtime, cycle, link, loop_log, limits, flag, progress=progress
                )
        with frozen_heap():
            exit_reason = runner()
        if envelope.reason is not None and exit_reason == envelope.reason:
            raise SafetyTrip(envelope.reason)
    except SafetyTrip as exc:
        exit_reason = str(exc)
        loop_log.event(None, "error", "safety_trip", exit_reason)
        raise
    except DriveFault as exc:
        exit_reason = f"drive fault: {exc}"
        loop_log.event(None, "error", "run_aborted", str(exc))
        raise
    except KeyboardInterrupt:
        exit_reason = "SIGINT"
        raise
    except BaseException as exc:
        exit_reason = f"exception: {type(exc).__name__}: {exc}"
        loop_log.event(None, "error", "run_aborted", exit_reason)
        raise
    finally:
        flag.stopping = True  # from here on a signal is noted, never fatal: stop and close finish
        wall_s = time.perf_counter() - t_start
        link.safe_stop()
        if drive is not None:
            if mode == "lockstep":
                while drive.service():  # the zero command, then the disable
                    pass
                # a stop that never arrived (bus off): the drive's own clock runs on until its
                # watchdog trips, as it would on hardware; the log's truth channel shows it
                for _ in range(config.drive.watchdog_periods + 1):
                    if not drive.enabled:
                        break
                    drive.advance_period()
            else:
                # the drive's own threads act on the stop sequence: give them a moment to
                # (bounded: a stop that never arrives leaves the watchdog to the drive)
                grace_end = time.monotonic() + EMBEDDED_RT_STOP_GRACE_S
                while drive.enabled and time.monotonic() < grace_end:
                    time.sleep(0.001)
                drive.stop()
        if rt_report is not None:
            restore_rt_settings(rt, rt_report)
        sys.setswitchinterval(switch_interval_s)
        stats: CycleStats = cycle.stats
        summary = RunSummary(
            name=config.name,
            log_path=str(log_path),
            mode=mode,
            dob_enabled=dob_enabled,
            exit_reason=exit_reason,
            samples=stats.samples,
            planned_samples=n_samples,
            duration_s=stats.samples * config.plant.period_ns * 1e-9,
            wall_time_s=wall_s,
            samples_per_s=stats.samples / wall_s if wall_s > 0 else 0.0,
            saturated_samples=stats.saturated,
            missing_samples=stats.missing,
            skipped_samples=stats.skipped,
            overruns=stats.overruns,
            unsequenced_periods=stats.unsequenced_periods,
            max_abs_current_A=stats.max_abs_applied_A,
            current_limit_A=config.drive.current_limit_A,
            compute_ns_max=stats.compute_ns_max,
            log_dropped_records=0,
            events=event_counts,
            rt_applied=rt_report.applied if rt_report else [],
            rt_refused=rt_report.refused if rt_report else [],
        )
        loop_log.flush()  # the frames and truth still queued
        if flag.ignored_signals:
            note = f"{flag.ignored_signals} signal(s) while stopping: noted, the stop went on"
            loop_log.event(None, "warning", "signal_while_stopping", note)
        loop_log.event(None, "info", "run_end", exit_reason)
        link.close()
        if drive_bus is not None:
            drive_bus.shutdown()
        loop_log.flush()  # the frames of the close
        log.close({k: json.dumps(v) if not isinstance(v, str) else v for k, v in summary.to_dict().items()})
        summary.log_dropped_records = log.stats.dropped_records
    return summary
