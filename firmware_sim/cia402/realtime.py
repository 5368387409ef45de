"""Real-time clock of the simulated CiA 402 drive: the host's SYNC frames are its clock.

One receive thread blocks on the bus and acts on each frame at its **arrival instant** on the
drive's monotonic clock (the bus timestamp converted to it when plausible, else the time it was
read), ``t = arrival - t0`` (to 10 us) with ``t0`` taken at :meth:`Cia402Realtime.start`. A SYNC therefore
integrates the physics up to when it arrived, not to a nominal ``k Ts``: a real plant does not
wait for a late SYNC, so SYNC jitter shows up as sampling jitter, as on hardware; the sample index
is the SYNC's position on the nominal grid (``round((t - t_first) / period)``, at least one more
than the last). Between frames the thread wakes for the drive's own timers (heartbeat producer,
SYNC-loss watchdog), judged up to the arrival of the last frame read, or up to now when none is
queued (so a stall of this thread with SYNCs waiting in the socket is not a SYNC loss). TPDOs
leave after ``sim.latency_us`` + jitter (seeded) or are lost with ``sim.loss_probability``.

An exception in the thread stops it; :meth:`check` and :meth:`stop` re-raise it in the caller.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import can

from dob_hil.config import Config
from firmware_sim.cia402.core import Cia402Core, TruthSink
from firmware_sim.impairments import FeedbackImpairment
from firmware_sim.threads import DriveThreads

RECV_POLL_S = 0.05  # the thread notices stop() within this
# bus timestamps further than this from now are not trusted (another clock); frames that waited in
# the socket while this thread was held up keep their own arrival within it
TIMESTAMP_PLAUSIBLE_NS = 1_000_000_000
# frames act at their arrival rounded to this: the plant caches one matrix exponential per offset
# inside a sub-step, so at its 1 us resolution the first SYNCs of a run would each compute new ones
# (tens of ms on a loaded machine); 10 us keeps that to a handful
ARRIVAL_RESOLUTION_NS = 10_000


def arrival_ns(msg: can.Message, now_mono_ns: int) -> int:
    """The frame's arrival on the monotonic clock: its bus timestamp when plausible, else now."""
    if msg.timestamp:
        stamped = round(msg.timestamp * 1e9) - (time.time_ns() - now_mono_ns)
        if abs(stamped - now_mono_ns) < TIMESTAMP_PLAUSIBLE_NS:
            return min(stamped, now_mono_ns)
    return now_mono_ns


class Cia402Realtime(DriveThreads):
    def __init__(self, bus: can.BusABC, config: Config, truth_sink: TruthSink | None = None) -> None:
        super().__init__()
        self.bus = bus
        self.core = Cia402Core(bus, config, lockstep=False, want_truth=truth_sink is not None)
        self.truth_sink = truth_sink
        sim = config.sim
        self.impairment = FeedbackImpairment(sim.latency_us, sim.jitter_us, sim.loss_probability, sim.seed)
        self.lock = threading.Lock()  # guards the core against the read-out from other threads

    def _on_start(self) -> None:
        with self.lock:
            self.core.power_on()

    def _thread_targets(self) -> tuple[tuple[str, Callable[[], None]], ...]:
        return (("firmware_sim-cia402", self._loop),)

    def _loop(self) -> None:
        core, t0, recv = self.core, self._t0_ns, self.bus.recv
        while not self._stop.is_set():
            with self.lock:
                timer = core.next_timer_ns()
            timeout = RECV_POLL_S
            if timer is not None:
                timeout = min(timeout, max(0.0, (timer - (time.monotonic_ns() - t0)) * 1e-9))
            msg = recv(timeout)
            now = time.monotonic_ns()
            with self.lock:
                if msg is None:
                    core.tick(now - t0)  # the queue is empty: nothing arrived until now
                else:
                    t = round((arrival_ns(msg, now) - t0) / ARRIVAL_RESOLUTION_NS) * ARRIVAL_RESOLUTION_NS
                    if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
                        core.stats.frames_ignored += 1
                    else:
                        core.on_frame(msg.arbitration_id, bytes(msg.data), t)
                    core.tick(t)  # timers only up to this frame: later ones may already be queued
                tpdos = core.take_tpdos()
                truth = core.take_truth()
            if tpdos:
                self._send_tpdos(tpdos, now)
            if truth is not None and self.truth_sink is not None:
                self.truth_sink(truth)

    def _send_tpdos(self, tpdos: list[tuple[int, bytes]], ready_ns: int) -> None:
        core, imp = self.core, self.impairment
        for cob_id, payload in tpdos:
            if imp.lost():
                with self.lock:
                    core.stats.tpdos_lost += 1
                continue
            if imp.delays:
                due = imp.due_ns(ready_ns)
                while (remaining := due - time.monotonic_ns()) > 0 and not self._stop.is_set():
                    time.sleep(remaining * 1e-9)
            core.network.send_message(cob_id, payload)
            with self.lock:
                core.stats.tpdos_sent += 1
