"""Lockstep clock of the simulated CiA 402 drive: a SYNC advances simulated time by one period.

:meth:`Cia402Lockstep.service` reads the frames pending on the drive's bus end (non-blocking) up
to and including a SYNC and acts on each in order, in the calling thread: SDO requests are
answered at once, NMT commands and RPDOs taken, and a SYNC integrates one period (none for the
first SYNC, which is t = 0), samples and sends the synchronous TPDOs. It is safe to call with
nothing pending and from any thread (a lock serialises callers and the drive's read-outs). While
the dob_hil host configures the drive it services it after every frame it sends, in its own
thread, so the SDO answer canopen waits for is there when it looks. :meth:`advance_period` lets one
period pass without a SYNC. TPDO loss (``sim.loss_probability``, seeded) applies; latency and
jitter need a wall clock and are ignored, as in the native lockstep drive.

In the cyclic phase the RPDO and SYNC of a period take one fused call
(:mod:`firmware_sim.cia402.fast`, the TPDO sent straight on the bus as a python-can Message)
where nothing unusual can happen; every other frame, and the rest of the period after one,
takes the general path (``Cia402Core.on_frame``). Both give the same frames, truth and state.
"""

from __future__ import annotations

import threading

import can

from dob_hil.config import Config
from firmware_sim.cia402.core import Cia402Core, TruthSink
from firmware_sim.cia402.fast import FastPeriod, FastPlan, fast_plan
from firmware_sim.impairments import FeedbackImpairment


class Cia402Lockstep:
    def __init__(
        self,
        bus: can.BusABC,
        config: Config,
        truth_sink: TruthSink | None = None,
        *,
        fast_path: bool = True,
    ) -> None:
        """``fast_path=False``: every frame takes the general path (tests compare the two)."""
        self.bus = bus
        self.core = Cia402Core(bus, config, lockstep=True, want_truth=truth_sink is not None)
        self.truth_sink = truth_sink
        sim = config.sim
        self.impairment = FeedbackImpairment(0.0, 0.0, sim.loss_probability, sim.seed)
        self.fast_path = fast_path
        lost = self.impairment.lost if sim.loss_probability > 0.0 else None
        self._fast = FastPeriod(self.core, bus, lost, truth_sink)
        self._plan: FastPlan | None = None  # rebuilt after any frame takes the general path
        self.lock = threading.Lock()
        with self.lock:
            self.core.power_on()  # the boot-up message goes out now

    def service(self) -> int:
        """Act on the frames pending on the bus, up to and including a SYNC; returns how many were read.

        Stopping after a SYNC (rather than reading until the queue is empty) saves an empty receive
        per period; frames sent after the SYNC are handled by the next call, as a real drive
        handles them in its next cycle. The cyclic RPDO and SYNC take the fused period
        (:mod:`firmware_sim.cia402.fast`) where it applies: the RPDO's values are held here until
        the SYNC, or handed to the core before any other frame acts.
        """
        recv, core = self.bus.recv, self.core
        n = 0
        n_rpdos = controlword = torque = 0
        with self.lock:
            plan = self._plan
            if plan is None and self.fast_path:
                plan = self._plan = fast_plan(core)
            while True:
                msg = recv(0.0)
                if msg is None:
                    if n_rpdos:
                        assert plan is not None
                        core.take_rpdo(plan.rpdo_layout, (controlword, torque), n_rpdos)
                    return n
                n += 1
                if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
                    core.stats.frames_ignored += 1
                    continue
                aid = msg.arbitration_id
                data = msg.data
                if plan is not None:
                    if aid == plan.rpdo_id and len(data) == plan.rpdo_size:
                        controlword, torque = plan.rpdo_unpack(data)
                        n_rpdos += 1
                        continue
                    if (
                        aid == plan.sync_id
                        and n_rpdos
                        and self._fast.sync(plan, controlword, torque, n_rpdos, data)
                    ):
                        if core._tpdos or core._truth is not None:  # an encoder fault took the tail
                            self._flush()
                        return n
                    if n_rpdos:
                        core.take_rpdo(plan.rpdo_layout, (controlword, torque), n_rpdos)
                        n_rpdos = 0
                    plan = self._plan = None
                core.on_frame(aid, bytes(data), core.time_ns)
                if core._tpdos or core._truth is not None:  # (most frames leave nothing to send)
                    self._flush()
                if aid == core.sync_cob_id:
                    return n

    def advance_period(self) -> None:
        """One period without a SYNC (the SYNC-loss watchdog counts it)."""
        with self.lock:
            self._plan = None
            self.core.advance_period()
            self._flush()

    def _flush(self) -> None:
        core = self.core
        for cob_id, payload in core.take_tpdos():
            if self.impairment.lost():
                core.stats.tpdos_lost += 1
            else:
                core.network.send_message(cob_id, payload)
                core.stats.tpdos_sent += 1
        truth = core.take_truth()
        if truth is not None and self.truth_sink is not None:
            self.truth_sink(truth)
