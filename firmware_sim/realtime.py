"""Real-time clock: the drive runs on its own timer thread, as a drive on its own crystal would.

* The **timer thread** wakes on absolute deadlines ``t0 + k Ts`` (sleep, then optionally spin the
  last ``spin_ns``: only where no other thread of the process needs the GIL, i.e. in the
  standalone process). The spin yields the CPU on every turn (``sched_yield``, which also lets
  the GIL go), so a thread of the same priority, such as the main thread handling SIGINT under
  SCHED_FIFO, or another process on a shared CPU, is never starved; a period that starts late
  (an overrun) is not spun at all, and under SCHED_FIFO the thread yields once per period even
  then (under the normal policy the kernel shares the CPU on its own, and a late drive keeps it). At each
  deadline it integrates the plant up to the nominal instant ``k Ts``, closes the period
  (watchdog, heartbeat), latches the encoder and sends FEEDBACK, delayed by the configured
  latency + jitter or dropped (seeded loss). If it falls more than a
  period behind it skips to the latest deadline and counts the skipped instants as overruns (the
  watchdog counts one period per processed instant, so the simulator's own stalls do not trip
  it).
* The **receive thread** blocks on ``bus.recv`` and acts on each frame at its arrival instant
  (the bus timestamp converted to the monotonic clock when plausible, else the time it was
  read): a command's current acts from its arrival (plus the input delay), so the period is
  integrated piecewise: old current up to the arrival, new current after.
* A frame the bus cannot deliver (``bus.recv`` raising ``CanError``, e.g. a datagram on the
  udp_multicast group that is not a python-can frame) is counted in ``stats.rx_errors`` and
  skipped; :data:`MAX_CONSECUTIVE_RX_ERRORS` in a row (a broken bus) stop the drive.
* An exception in either thread stops both; :meth:`RealtimeClock.check` and
  :meth:`RealtimeClock.stop` re-raise it in the caller's thread.

Simulated time is ``time.monotonic_ns() - t0`` with ``t0`` taken at :meth:`RealtimeClock.start`.
"""

from __future__ import annotations

import collections
import ctypes
import os
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import can

from dob_hil.config import Config
from dob_hil.link.protocol import DriveState, FrameKind
from firmware_sim.behaviour import REFERENCE, DriveBehaviour
from firmware_sim.clocked import CoreReadout
from firmware_sim.core import DriveCore, DriveStats, FrameResult, TruthSink
from firmware_sim.impairments import FeedbackImpairment
from firmware_sim.threads import DriveThreads, yield_cpu

RECV_POLL_S = 0.05  # the receive thread notices stop() within this
TIMESTAMP_PLAUSIBLE_NS = 50_000_000  # bus timestamps further than this from now are not trusted
MAX_CONSECUTIVE_RX_ERRORS = 1000  # bus.recv raising this often in a row: the bus is broken


def _realtime_policy() -> bool:
    """This thread runs under SCHED_FIFO or SCHED_RR (where same-priority threads never preempt it)."""
    try:
        return os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR)
    except (AttributeError, OSError):
        return False


def _set_timer_slack_1ns() -> None:
    """Linux: this thread's timer slack to 1 ns (default 50 us), so sleeps end on time."""
    if sys.platform != "linux":
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(29, 1, 0, 0, 0)  # PR_SET_TIMERSLACK
    except (OSError, AttributeError):
        pass


Outgoing = list[tuple[int, bytes]]  # (arbitration id, payload)


class ThreadedDriveClock(DriveThreads):
    """The two threads of a real-time simulated drive, around a firmware core the subclass owns.

    Subclasses set ``_stats`` (the counters the clock updates), ``_rx_ids`` (the ids the firmware
    acts on) and ``_feedback_ids``, and implement :meth:`_tick` (one sample instant: the frames to
    send now, the FEEDBACK frames to send when due, the truth) and :meth:`_on_rx` (one received
    frame, under the lock: the frames to send in answer). :class:`RealtimeClock` is one drive;
    :class:`firmware_sim.axes.realtime.MultiAxisRealtimeClock` is several nodes on one clock.
    """

    core: CoreReadout
    _stats: DriveStats
    _rx_ids: frozenset[int]
    _feedback_ids: frozenset[int]

    def __init__(
        self, bus: can.BusABC, config: Config, truth_sink: Callable[[Any], None] | None, *, spin_ns: int
    ) -> None:
        super().__init__(spin_ns=spin_ns)
        self.bus = bus
        self.truth_sink = truth_sink
        self.period_ns = config.plant.period_ns
        sim = config.sim
        self.impairment = FeedbackImpairment(sim.latency_us, sim.jitter_us, sim.loss_probability, sim.seed)
        self._lock = threading.Lock()  # guards the core
        self._send_lock = threading.Lock()
        self._commanded = False  # a valid command since the last sample

    # --- read-out ------------------------------------------------------------------------------
    def snapshot(self) -> tuple[DriveState, int, tuple[float, ...], int, DriveStats]:
        """(state, period index, true plant state, time, a copy of the counters), consistent."""
        with self._lock:
            c = self.core
            return c.state, c.period_index, c.plant.state, c.time_ns, DriveStats(**vars(c.stats))

    # --- the firmware, per subclass ----------------------------------------------------------------
    def _tick(self, k: int) -> tuple[Outgoing, Outgoing, Any]:
        """Sample instant ``k`` (under the lock): (frames now, FEEDBACK frames when due, truth)."""
        raise NotImplementedError

    def _on_rx(self, arbitration_id: int, data: bytes | bytearray, t_ns: int) -> Outgoing:
        """A frame of ``_rx_ids`` arrived at drive time ``t_ns`` (under the lock): frames to send."""
        raise NotImplementedError

    def _silent(self) -> bool:
        raise NotImplementedError

    # --- threads -------------------------------------------------------------------------------
    def _thread_targets(self) -> tuple[tuple[str, Callable[[], None]], ...]:
        return (("firmware_sim-timer", self._timer_loop), ("firmware_sim-rx", self._rx_loop))

    def _timer_loop(self) -> None:
        _set_timer_slack_1ns()
        realtime_policy = _realtime_policy()
        period_ns, t0 = self.period_ns, self._t0_ns
        outbox: collections.deque[tuple[int, int, bytes]] = collections.deque()  # (due, id, payload)
        delays = self.impairment.delays
        k = 0
        while not self._stop.is_set():
            deadline = t0 + k * period_ns
            while outbox and outbox[0][0] <= deadline:
                self._wait_until(outbox[0][0])
                _, aid, payload = outbox.popleft()
                self._send(aid, payload)
            if not self._wait_until(deadline) and realtime_policy:
                yield_cpu()  # late under SCHED_FIFO: still let a thread of the same priority run
            if self._stop.is_set():
                return
            with self._lock:
                frames, feedback, truth = self._tick(k)
            for aid, data in frames:
                self._send(aid, data)
            if feedback:
                due = self.impairment.due_ns(deadline) if delays else deadline
                for aid, payload in feedback:
                    if due <= time.monotonic_ns() and not outbox:
                        self._send(aid, payload)
                    else:
                        outbox.append((due, aid, payload))
            if truth is not None and self.truth_sink is not None:
                self.truth_sink(truth)
            k += 1
            latest = (time.monotonic_ns() - t0) // period_ns
            if latest > k:
                with self._lock:
                    self._stats.overruns += latest - k
                k = latest

    def _rx_loop(self) -> None:
        t0 = self._t0_ns
        rx_ids = self._rx_ids
        recv = self.bus.recv
        errors_in_row = 0
        while not self._stop.is_set():
            try:
                msg = recv(RECV_POLL_S)
            except can.CanError:
                errors_in_row += 1
                with self._lock:
                    self._stats.rx_errors += 1
                if errors_in_row >= MAX_CONSECUTIVE_RX_ERRORS:
                    raise
                continue
            errors_in_row = 0
            if msg is None:
                continue
            aid = msg.arbitration_id
            if aid not in rx_ids or msg.is_extended_id or msg.is_error_frame:
                continue  # includes our own frames echoed back by udp_multicast
            if msg.is_remote_frame:
                continue
            now = time.monotonic_ns()
            arrival = now
            if msg.timestamp:
                stamped = round(msg.timestamp * 1e9) - (time.time_ns() - now)
                if abs(stamped - now) < TIMESTAMP_PLAUSIBLE_NS:
                    arrival = min(stamped, now)
            with self._lock:
                frames = self._on_rx(aid, msg.data, arrival - t0)
            for out_id, data in frames:
                self._send(out_id, data)

    def _send(self, arbitration_id: int, payload: bytes) -> None:
        if self._silent():
            with self._lock:
                self._stats.frames_suppressed += 1
            return
        msg = can.Message(arbitration_id=arbitration_id, data=payload, is_extended_id=False)
        with self._send_lock:
            try:
                self.bus.send(msg)
            except can.CanError:
                with self._lock:
                    self._stats.send_failures += 1
                return
        if arbitration_id in self._feedback_ids:
            with self._lock:
                self._stats.feedback_sent += 1


class RealtimeClock(ThreadedDriveClock):
    """One simulated drive (:class:`~firmware_sim.core.DriveCore`) on the real-time clock."""

    def __init__(
        self,
        bus: can.BusABC,
        config: Config,
        truth_sink: TruthSink | None = None,
        *,
        spin_ns: int = 0,
        behaviour: DriveBehaviour = REFERENCE,
    ) -> None:
        super().__init__(bus, config, truth_sink, spin_ns=spin_ns)
        window = min(config.drive.watchdog_periods, 64)
        self.core: DriveCore = DriveCore(
            config, accept_window=max(window, 2), want_truth=truth_sink is not None, behaviour=behaviour
        )
        self._node_id = self.core.node_id
        self._stats = self.core.stats
        self._rx_ids = frozenset((self.core.command_id, self.core.control_id))
        self._feedback_id = FrameKind.FEEDBACK + self._node_id
        self._feedback_ids = frozenset((self._feedback_id,))

    # --- the firmware --------------------------------------------------------------------------
    def _silent(self) -> bool:
        return self.core.silent

    def _tick(self, k: int) -> tuple[Outgoing, Outgoing, Any]:
        core, node = self.core, self._node_id
        core.integrate_to(k * self.period_ns)
        if k > 0:
            core.period_boundary(self._commanded)
        self._commanded = False
        frames = [(kind + node, data) for kind, data in core.take_outgoing()]
        payload, truth = core.sample()
        if self.impairment.lost():
            core.stats.feedback_lost += 1
            return frames, [], truth
        return frames, [(self._feedback_id, payload)], truth

    def _on_rx(self, arbitration_id: int, data: bytes | bytearray, t_ns: int) -> Outgoing:
        core = self.core
        result = core.on_frame(arbitration_id, data, max(t_ns, core.time_ns))
        if result is FrameResult.COMMAND:
            self._commanded = True
        node = self._node_id
        return [(kind + node, payload) for kind, payload in core.take_outgoing()]
