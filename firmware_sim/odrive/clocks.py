"""The simulated ODrive's two clocks: lockstep (driven by the host's frames) and real time.

Lockstep: :meth:`OdriveLockstep.service` drains the frames pending on the drive's bus end and
acts on each at the current simulated instant. Set_Axis_State is answered by a heartbeat at once
(the drive's clock stands still until the host answers, so the heartbeat a real drive sends
within ``heartbeat_msg_rate_ms`` comes now). With cyclic estimates (``encoder_msg_rate_ms`` =
Ts, drive-clocked) entering closed loop sends the estimates of the current instant, and a
Set_Input_Torque answering the last estimates integrates one period (the torque acting from the
sample instant), closes it (watchdog, heartbeat) and sends the next estimates; torque inputs
before any estimates (the enable sequence) only set the input, and an RTR is answered with the
estimates of the current instant. Without them (``encoder_msg_rate_ms = 0``, host-clocked) the
RTR is the clock: the first is answered with the estimates of the current instant, each later
one integrates a period first (torque inputs in between act from the sample instant).
:meth:`OdriveLockstep.advance_period` runs a period without a torque input (estimates only if
cyclic). ``sim.loss_probability`` drops estimates (seeded).

The lockstep per-period path is fused (``FAST_PATH``, :attr:`OdriveLockstep.fast`): a
well-formed Set_Input_Torque and an RTR are handled inside :meth:`OdriveLockstep.service`, a
host-clocked period (integration with one held current, the period boundary, heartbeat) and its
estimates and ground truth take two calls, with the core's arithmetic in the core's order. Any
other frame, a current change inside the period, a plant of other than two states or a
non-finite position takes the core's general methods. Both give the same frames, truth and
counters (tests/odrive/test_fast_path.py runs them side by side); ``FAST_PATH = False`` forces
the general path.

Real time: a timer thread wakes on absolute deadlines ``t0 + k Ts``, integrates to ``k Ts``,
closes the period and sends the cyclic estimates (if configured); a receive thread acts on each
frame at its arrival (a torque acts from its arrival, an RTR is answered with the estimates
sampled at its arrival). Exceptions in either thread stop both and are re-raised by
:meth:`OdriveRealtime.check` / :meth:`OdriveRealtime.stop`.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from collections.abc import Callable
from typing import Any, cast

import can

from dob_hil.config import Config
from dob_hil.link.message import data_frame
from dob_hil.link.odrive import codec
from dob_hil.link.odrive.codec import DLC, AxisState, CmdId, ODriveError
from dob_hil.link.protocol import DriveState
from firmware_sim.impairments import FeedbackImpairment
from firmware_sim.odrive.core import OdriveCore, OdriveStats, TruthSink
from firmware_sim.threads import DriveThreads
from firmware_sim.truth import GroundTruth

RECV_POLL_S = 0.05
FAST_PATH = True  # False: every frame and period through the general path (the fast path's tests)
_CLOSED_LOOP = AxisState.CLOSED_LOOP_CONTROL
_FAULT, _ENABLED, _DISABLED = DriveState.FAULT, DriveState.ENABLED, DriveState.DISABLED
_TORQUE = struct.Struct("<f4x")  # Set_Input_Torque's payload (codec.decode_set_input_torque)
_ESTIMATES = struct.Struct("<ff")
_F32_MAX = codec.F32_MAX
_INF = math.inf  # (a module constant: one load on the per-period path)


class OdriveLockstep:
    def __init__(self, bus: can.BusABC, config: Config, truth_sink: TruthSink | None = None) -> None:
        self.bus = bus
        self.core = core = OdriveCore(config, want_truth=truth_sink is not None)
        self.truth_sink = truth_sink
        sim = config.sim
        self.impairment = FeedbackImpairment(0.0, 0.0, sim.loss_probability, sim.seed)
        self._awaiting = False  # estimates went out; the next torque input closes the period
        self._sampled_at = -1  # the instant the last estimates were taken at
        self._truth_at = -1  # the instant of the last ground-truth record
        self.fast = FAST_PATH  # the per-frame and per-period fast paths (module docstring)
        self._torque_id = core.ids[CmdId.SET_INPUT_TORQUE]
        c_row = core.plant.c_2state
        self._rows_2 = (  # (C row, C A row) of a two-state plant, for the inline sample
            (*c_row, *core.vel_row) if c_row is not None and len(core.vel_row) == 2 else None
        )

    def service(self) -> int:
        """Act on every frame pending on the drive's bus end (returns how many were read).

        Fast path (:attr:`fast`): a well-formed Set_Input_Torque and an RTR Get_Encoder_Estimates
        are handled inline, and the period an RTR closes goes through :meth:`_period_fast`; every
        other frame (and every frame with ``fast`` off) goes through :meth:`_on_message`.
        """
        recv = self.bus.recv
        if not self.fast:
            n = 0
            while (msg := recv(0.0)) is not None:
                n += 1
                if self._on_message(msg):
                    return n
            return n
        core = self.core
        torque_id, estimates_id = self._torque_id, core.estimates_id
        n = 0
        while (msg := recv(0.0)) is not None:
            n += 1
            if not (msg.is_error_frame or msg.is_extended_id):
                aid = msg.arbitration_id
                if aid == torque_id and not msg.is_remote_frame:
                    data = msg.data
                    if len(data) == DLC:  # core._on_set_input_torque, inline
                        torque: float = _TORQUE.unpack(data)[0]
                        if -_INF < torque < _INF:
                            core.input_torque_Nm = torque
                            core.stats.commands_accepted += 1
                            if core.axis_state is _CLOSED_LOOP:
                                core.fed = True
                                current_A = torque / core.kt  # core.apply, inline: within the limit
                                if core.torque_passthrough and abs(current_A) <= core.current_limit_A:
                                    path = core.path  # path.schedule(core.time_ns, current_A), inline:
                                    times = path._times_ns  # its common case, the latest change
                                    t = core.time_ns
                                    if not times or t >= times[-1]:
                                        times.append(t)
                                        path._currents_A.append(current_A)
                                    else:
                                        path.schedule(t, current_A)
                                else:
                                    core.apply(core.time_ns)
                            if self._awaiting and core.cyclic:
                                self._run_period()
                                return n
                            if core.out:
                                self._send_outgoing()
                            continue
                elif aid == estimates_id and msg.is_remote_frame:
                    core.stats.rtr_answered += 1
                    if core.cyclic or self._sampled_at != core.time_ns:
                        self._send_estimates()  # the estimates of this instant
                        continue
                    self._period_fast()  # host-clocked: each RTR after the first is the next instant
                    return n
            if self._on_message(msg):
                return n
        return n

    def _on_message(self, msg: can.Message) -> bool:
        """The general path of one frame; True if it closed a period (service returns)."""
        core = self.core
        if msg.is_error_frame:
            core.stats.rx_errors += 1
            return False
        if msg.is_extended_id:
            core.stats.frames_ignored += 1
            return False
        was_closed = core.closed_loop
        cmd = core.on_frame(msg.arbitration_id, msg.data, msg.is_remote_frame, core.time_ns)
        if cmd is CmdId.SET_INPUT_TORQUE and self._awaiting and core.cyclic:
            self._run_period()
            return True
        if cmd is CmdId.GET_ENCODER_ESTIMATES:
            core.stats.rtr_answered += 1
            if core.cyclic or self._sampled_at != core.time_ns:
                self._send_estimates()  # the estimates of this instant
                return False
            self._run_period()  # host-clocked: each RTR after the first is the next instant
            return True
        if cmd is CmdId.SET_AXIS_STATE:
            core.heartbeat_now()
            self._send_outgoing()
            if core.closed_loop and not was_closed and core.cyclic:
                self._send_estimates()
        else:
            self._send_outgoing()
        return False

    def _period_fast(self) -> None:
        """:meth:`_run_period` with its estimates (a host-clocked RTR after the first), in one call:
        :meth:`OdriveCore.integrate_to` for one held current and :meth:`OdriveCore.period_boundary`
        inline, in the same order (any other integration through the core). The same records as
        the general path: tests/odrive/test_fast_path.py."""
        core = self.core
        t = core.time_ns
        t1 = t + core.period_ns
        path = core.path
        if path.advance_held(core.plant, t, t1):  # no current change due inside the period
            core.time_ns = t1
        else:
            core.integrate_to(t1)
        faults = core.faults
        if faults is not None:
            faults.on_period(cast(Any, core), t1 // core.period_ns)
            core.silent = faults.silent
        if core.axis_state is _CLOSED_LOOP:  # the watchdog
            missed = 0 if core.fed else core.missed + 1
            core.missed = missed
            core.fed = False
            if missed >= core.watchdog_periods:
                core.set_error(ODriveError.WATCHDOG_TIMER_EXPIRED, t1)
        if t1 >= core.next_heartbeat_ns:
            core.heartbeat_if_due()
        if core.out:  # a heartbeat (or an error's) goes out before the estimates
            self._send_outgoing()
        self._send_estimates()

    def _run_period(self, *, sample: bool = True) -> None:
        core = self.core
        core.integrate_to(core.time_ns + core.period_ns)
        core.period_boundary()
        self._send_outgoing()
        if sample:
            self._send_estimates()
        elif self.truth_sink is not None and self.core.want_truth:
            truth = self.core.truth()  # the log's truth channel follows the drive's clock
            self._truth_at = self.core.time_ns
            self.truth_sink(truth)

    def advance_period(self) -> None:
        """One period without a torque input; the estimates follow if they are cyclic.

        Host-clocked, this is a period whose trigger never arrived: its instant counts as taken,
        so the next RTR is the next instant (it integrates a period first), as if this one had
        been answered. Otherwise every later sample would be the previous instant's."""
        self._run_period(sample=self.core.cyclic)
        if not self.core.cyclic:
            self._sampled_at = self.core.time_ns

    def _send_estimates(self) -> None:
        """Get_Encoder_Estimates of this instant (unless lost or silenced) and its ground truth.

        Fast path (:attr:`fast`, a two-state plant, a finite position):
        :meth:`OdriveCore.estimates` and :meth:`OdriveCore.truth` inline, the same arithmetic in
        the same order; anything else samples through the core."""
        core = self.core
        rows = self._rows_2
        x = tuple(core.plant._x)  # plant.state without the property
        pos_unit = math.nan
        if rows is not None and self.fast:
            c0, c1, v0, v1 = rows
            pos_unit = c0 * x[0] + c1 * x[1]  # plant.position() of a two-state plant
        if -_INF < pos_unit < _INF:
            t = core.time_ns
            faults = core.faults
            offset_counts = 0 if faults is None else faults.counts(t // core.period_ns, 0)
            std = core.noise_std_counts
            noise_counts = core.rng.normal(0.0, std) if std > 0 else 0.0
            tpu = core.turns_per_unit
            pos_turns = pos_unit * tpu + (offset_counts + noise_counts) / core.cpr
            # the core's sum() over C A x: the same order, from the same int 0
            vel_turns = (0 + v0 * x[0] + v1 * x[1]) * tpu
            core.stats.samples += 1
            if -_F32_MAX <= pos_turns <= _F32_MAX and -_F32_MAX <= vel_turns <= _F32_MAX:
                payload = _ESTIMATES.pack(pos_turns, vel_turns)
            else:
                payload = core.pack_estimates(pos_turns, vel_turns)
            truth: GroundTruth | None = None
            if core.want_truth:  # core.truth(), inline
                d = core.disturbance
                t_s = t * 1e-9
                origin_s = d.origin_s
                w_A = 0.0 if origin_s is None or t_s < origin_s else d.inner.value_A(t_s - origin_s)
                # core.drive_state, inline
                if core.axis_error:
                    drive_state = _FAULT
                else:
                    drive_state = _ENABLED if core.axis_state is _CLOSED_LOOP else _DISABLED
                state = (t // core.period_ns, t, x, w_A, core.path.held_A, drive_state)
                truth = tuple.__new__(GroundTruth, state)
        else:
            payload, truth = core.estimates()
            t = core.time_ns
        self._sampled_at = t
        if core.out:
            self._send_outgoing()  # an error the sample raised goes out first
        self._awaiting = True
        impairment = self.impairment
        if impairment.loss_probability > 0.0 and impairment.lost():
            core.stats.feedback_lost += 1
        elif core.silent:
            core.stats.frames_suppressed += 1
        else:  # _send, inline: stamped with the simulated time
            self.bus.send(data_frame(t * 1e-9, core.estimates_id, payload))
            core.stats.feedback_sent += 1
        if truth is not None and self.truth_sink is not None and self._truth_at != t:
            self._truth_at = t
            self.truth_sink(truth)

    def _send_outgoing(self) -> None:
        if not self.core.out:  # the common case: nothing queued (no list swap)
            return
        for aid, payload in self.core.take_outgoing():
            self._send(aid, payload)

    def _send(self, arbitration_id: int, payload: bytes) -> bool:
        if self.core.silent:
            self.core.stats.frames_suppressed += 1
            return False
        # stamped with the simulated time, as a drive's controller stamps on its own clock
        stamp_s = self.core.time_ns * 1e-9
        self.bus.send(can.Message(stamp_s, arbitration_id, False, False, False, None, None, payload))
        return True


class OdriveRealtime(DriveThreads):
    def __init__(
        self, bus: can.BusABC, config: Config, truth_sink: TruthSink | None = None, *, spin_ns: int = 0
    ) -> None:
        super().__init__(spin_ns=spin_ns)
        self.bus = bus
        self.core = OdriveCore(config, want_truth=truth_sink is not None)
        self.truth_sink = truth_sink
        sim = config.sim
        self.impairment = FeedbackImpairment(0.0, 0.0, sim.loss_probability, sim.seed)
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()

    def _thread_targets(self) -> tuple[tuple[str, Callable[[], None]], ...]:
        return (("odrive-timer", self._timer_loop), ("odrive-rx", self._rx_loop))

    def snapshot(self) -> tuple[bool, int, tuple[float, ...], int, OdriveStats]:
        with self._lock:
            c = self.core
            return c.closed_loop, c.period_index, c.plant.state, c.time_ns, OdriveStats(**vars(c.stats))

    def _timer_loop(self) -> None:
        core, period_ns, t0 = self.core, self.core.period_ns, self._t0_ns
        k = 0
        while not self._stop.is_set():
            self._wait_until(t0 + k * period_ns)
            if self._stop.is_set():
                return
            with self._lock:
                core.integrate_to(k * period_ns)
                if k > 0:
                    core.period_boundary()
                payload, truth = core.estimates()
                frames = core.take_outgoing()
                lost = self.impairment.lost()
                if lost:
                    core.stats.feedback_lost += 1
            for aid, data in frames:
                self._send(aid, data)
            if not lost and core.cyclic:
                self._send(core.estimates_id, payload)
            if truth is not None and self.truth_sink is not None:
                self.truth_sink(truth)
            k += 1
            latest = (time.monotonic_ns() - t0) // period_ns
            if latest > k:
                with self._lock:
                    core.stats.overruns += latest - k
                k = latest

    def _rx_loop(self) -> None:
        core, t0 = self.core, self._t0_ns
        recv = self.bus.recv
        while not self._stop.is_set():
            msg = recv(RECV_POLL_S)
            if msg is None or msg.is_extended_id:
                continue
            if msg.is_error_frame:
                with self._lock:
                    core.stats.rx_errors += 1
                continue
            if msg.arbitration_id >> 5 != core.node_id:
                continue  # another node's frame
            if not msg.is_remote_frame and msg.arbitration_id in (core.estimates_id, core.heartbeat_id):
                continue  # our own frames echoed back (udp_multicast)
            now = time.monotonic_ns()
            answer: bytes | None = None
            with self._lock:
                t = max(now - t0, core.time_ns)
                cmd = core.on_frame(msg.arbitration_id, msg.data, msg.is_remote_frame, t)
                if cmd is CmdId.GET_ENCODER_ESTIMATES:
                    core.integrate_to(t)
                    answer, _ = core.estimates()
                    core.stats.rtr_answered += 1
                frames = core.take_outgoing()
            for aid, data in frames:
                self._send(aid, data)
            if answer is not None:
                self._send(core.estimates_id, answer)

    def _send(self, arbitration_id: int, payload: bytes) -> None:
        if self.core.silent:
            with self._lock:
                self.core.stats.frames_suppressed += 1
            return
        msg = can.Message(arbitration_id=arbitration_id, data=payload, is_extended_id=False)
        with self._send_lock:
            try:
                self.bus.send(msg)
            except can.CanError:
                with self._lock:
                    self.core.stats.send_failures += 1
                return
        if arbitration_id == self.core.estimates_id:
            with self._lock:
                self.core.stats.feedback_sent += 1
