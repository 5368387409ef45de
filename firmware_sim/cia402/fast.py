"""The lockstep drive's fused period: one call for the common case of a cyclic SYNC.

In the cyclic phase of a lockstep run every period brings the same two frames from the host, the
RPDO of the standard mapping (controlword 0x6040, target torque 0x6071) and a SYNC, and the drive
answers with the TPDO of the standard mapping (statusword 0x6041, position 0x6064). The general
path (:meth:`firmware_sim.cia402.core.Cia402Core.on_frame`) handles that through the object
dictionary's layouts, a dict of pending values, the power state machine and a generic TPDO queue,
about a hundred Python calls per period. :class:`FastPeriod` does the same work as straight-line
code, with the same records, frames and state as the general path, for the case where nothing
else can happen:

* the plan (:func:`fast_plan`, rebuilt whenever a frame takes the general path): the lockstep
  clock is running, the plant origin set, NMT OPERATIONAL, no injected faults configured, the drive
  not muted, RPDO and TPDO layouts are the standard ones (one TPDO, transmission type 1, no SYNC
  start value), the SYNC COB-ID distinct from every other frame the drive takes;
* per SYNC (:meth:`FastPeriod.sync`, checked before anything changes): OPERATION ENABLED, an RPDO
  received since the previous SYNC whose controlword is the one already taken and leaves the
  state where it is, no other value pending, the SYNC's length as 0x1019 expects.

Anything else returns False and the caller takes the general path for that frame, which is the
specification; tests compare the two paths record for record. An encoder fault (non-finite plant
position) discovered half-way hands the rest of the period to the general path's tail.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import can

from dob_hil.link.message import data_frame
from dob_hil.link.protocol import DriveState
from firmware_sim.cia402 import objects as ob
from firmware_sim.cia402.pdo import Layout
from firmware_sim.cia402.power import (
    CW_FAULT_RESET,
    CW_HALT,
    STATUS_BITS,
    SW_FOLLOWS_COMMAND,
    SW_INTERNAL_LIMIT,
    SW_REMOTE,
    PowerState,
)
from firmware_sim.truth import GroundTruth

if TYPE_CHECKING:
    from firmware_sim.cia402.core import Cia402Core, TruthSink

RPDO_OBJECTS = ((ob.CONTROLWORD, 0), (ob.TARGET_TORQUE, 0))
TPDO_OBJECTS = ((ob.STATUSWORD, 0), (ob.POSITION_ACTUAL, 0))
_OE = PowerState.OPERATION_ENABLED
_SW_OE = STATUS_BITS[_OE] | SW_REMOTE
_ENABLED = DriveState.ENABLED
_CW_ENABLE_OPERATION = 0x000F  # the command bits of "enable operation" (power._command)
_I32_MIN, _I32_MAX = -(2**31), 2**31 - 1
_new_tuple = tuple.__new__


@dataclass(frozen=True, slots=True)
class FastPlan:
    """What the fused period needs from the drive's settings (valid until a general-path frame)."""

    rpdo_id: int
    rpdo_layout: Layout
    rpdo_size: int
    rpdo_unpack: Callable[[bytearray], tuple[int, ...]]
    sync_id: int
    sync_len: int  # 0, or 1 with the SYNC counter (0x1019 > 0)
    tpdo_id: int
    tpdo_pack: Callable[..., bytes]
    # settings only a general-path frame (an SDO write, NMT) changes, read once per plan
    period_ns: int
    origin_ns: int
    extra_delay_ns: int
    mode_cst: bool
    max_torque: int
    rated_current_mA: int
    position_row: tuple[float, float] | None  # C[0] of a 2-state plant (plant.position, inline)


def fast_plan(core: Cia402Core) -> FastPlan | None:
    """The plan for the current settings, or None where the fused period does not apply."""
    if (
        not core.lockstep
        or not core._clock_started
        or core.origin_ns is None
        or core.faults is not None
        or core.network.muted
        or core.node.nmt.state != "OPERATIONAL"
    ):
        return None
    layouts = core.layouts
    if layouts.stale:  # the general path rebuilds them at its next PDO
        return None
    sync_id = core.sync_cob_id
    tpdos = layouts.tpdos
    if len(tpdos) != 1 or len(core._tpdo_syncs) != 1:
        return None
    tpdo = tpdos[0]
    if tpdo.objects != TPDO_OBJECTS or tpdo.trans_type != 1 or tpdo.sync_start:
        return None
    rpdo = next((lay for lay in layouts.rpdos.values() if lay.objects == RPDO_OBJECTS), None)
    if rpdo is None or rpdo.trans_type > 240:
        return None
    if rpdo.cob_id in (0, sync_id, core.sdo_rx_id) or sync_id in (0, core.sdo_rx_id):
        return None
    return FastPlan(
        rpdo_id=rpdo.cob_id,
        rpdo_layout=rpdo,
        rpdo_size=rpdo.size,
        rpdo_unpack=rpdo.packer.unpack,
        sync_id=sync_id,
        sync_len=1 if core.sync_overflow > 0 else 0,
        tpdo_id=tpdo.cob_id,
        tpdo_pack=tpdo.packer.pack,
        period_ns=core.period_ns,
        origin_ns=core.origin_ns,
        extra_delay_ns=core.extra_delay_ns,
        mode_cst=core.mode == ob.MODE_CST,
        max_torque=core.max_torque,
        rated_current_mA=core.rated_current_mA,
        position_row=core.plant.c_2state,
    )


class FastPeriod:
    """The fused SYNC of one lockstep drive (module docstring)."""

    def __init__(
        self,
        core: Cia402Core,
        bus: can.BusABC,
        lost: Callable[[], bool] | None,
        truth_sink: TruthSink | None,
    ) -> None:
        self.core = core
        self.bus = bus
        self.lost = lost  # the TPDO loss draw; None without loss
        self.truth_sink = truth_sink

    def sync(self, plan: FastPlan, controlword: int, torque: int, n_rpdos: int, data: bytearray) -> bool:
        """The SYNC ``data`` after ``n_rpdos`` RPDOs (the last one: ``controlword``, ``torque``):
        integrate, sample, send the TPDO and the truth, take the RPDO. False (nothing changed) where
        the general path must act."""
        core = self.core
        power = core.power
        if (
            power.state is not _OE
            or controlword != power.controlword
            # taken again in OPERATION ENABLED it changes nothing: a fault reset word (bit 7: no
            # command is taken) or "enable operation" (no transition out of OPERATION ENABLED)
            or not (
                controlword & CW_FAULT_RESET or controlword & _CW_ENABLE_OPERATION == _CW_ENABLE_OPERATION
            )
            or len(data) != plan.sync_len
            or core._pending
        ):
            return False
        stats = core.stats
        stats.syncs += 1
        stats.rpdos += n_rpdos
        # --- integrate to the SYNC instant (Cia402Core._integrate_to) ---
        now_ns = core.time_ns
        period_ns = plan.period_ns
        t = now_ns + period_ns
        origin = plan.origin_ns
        path, plant = core.path, core.plant
        tau = now_ns - origin
        if path.advance_held(plant, tau, tau + period_ns):  # one current over the whole period
            core.time_ns = t
        else:
            core._integrate_to(t)
        period_index = t // period_ns
        core.period_index = period_index
        core._last_sync_ns = t
        core._missed_sync = 0
        if core._watch_armed:
            core._missed_rpdo = 0  # an RPDO came in this period
        held_A = path.held_A
        # --- sample (Cia402Core._sample) ---
        row = plan.position_row
        try:
            if row is not None:
                x = plant._x
                position = row[0] * x[0] + row[1] * x[1]  # plant.position() of a 2-state plant
            else:
                position = plant.position()  # may raise too (math.fsum of +inf and -inf)
            counts = core.encoder.read(position)
        except ValueError:  # not finite or beyond any count, an encoder fault: the general tail
            core._rpdo_since_sync = True
            core._pending.update(zip(RPDO_OBJECTS, (controlword, torque), strict=True))
            core._sync_tail(t, data[0] if data else None)  # the watchdog's share again: idempotent
            return True
        last_t = core._sample_t_ns
        if last_t is not None and t > last_t:
            step = ((counts - core.counts + 2**31) % 2**32) - 2**31
            v = round(step * 1e9 / (t - last_t))
            core.velocity = _I32_MIN if v < _I32_MIN else _I32_MAX if v > _I32_MAX else v
        core._sample_t_ns = t
        core.counts = counts
        # --- the TPDO (Cia402Core._queue_tpdos with the statusword of Cia402Core.statusword) ---
        sw = _SW_OE
        follows = plan.mode_cst and not controlword & CW_HALT
        if follows:
            sw |= SW_FOLLOWS_COMMAND
        if core.saturated:
            sw |= SW_INTERNAL_LIMIT
        payload = plan.tpdo_pack(sw, counts)
        core._tpdo_syncs[0] += 1
        core._tpdo_last[0] = payload
        # --- take the RPDO (Cia402Core._apply, _controlword, _update_current) ---
        core.target_torque = torque
        effective = torque if follows else 0
        limit = plan.max_torque
        clamped = -limit if effective < -limit else limit if effective > limit else effective
        core.saturated = clamped != effective
        t_apply = t - origin + plan.extra_delay_ns
        current_A = clamped * plan.rated_current_mA * 1e-6
        times = path._times_ns
        if not times or t_apply >= times[-1]:  # CurrentPath.schedule's common case
            times.append(t_apply)
            path._currents_A.append(current_A)
        else:
            path.schedule(t_apply, current_A)
        core._rpdo_since_sync = False
        core._watch_armed = True
        # --- heartbeat first (sent from within the SYNC), then the TPDO and the truth (the flush) ---
        nmt = core.node.nmt
        next_heartbeat = core._next_heartbeat_ns
        if nmt.heartbeat_changed or (next_heartbeat is not None and t >= next_heartbeat):
            core._heartbeat(t)
        lost = self.lost
        if lost is not None and lost():
            stats.tpdos_lost += 1
        else:
            try:
                # the frame canopen's Network.send_message builds (dob_hil.link.message)
                self.bus.send(data_frame(0.0, plan.tpdo_id, payload))
            except can.CanError:
                core.network.send_failures += 1
            stats.tpdos_sent += 1
        sink = self.truth_sink
        if sink is not None:
            w = core.disturbance.value_A((t - origin) * 1e-9)
            sink(_new_tuple(GroundTruth, (period_index, t, tuple(plant._x), w, held_A, _ENABLED)))
        return True
