"""The simulated CiA 402 drive's firmware, independent of any clock: frames in, frames and truth out.

A clock (:mod:`firmware_sim.cia402.lockstep` or :mod:`firmware_sim.cia402.realtime`) hands every
received frame to :meth:`Cia402Core.on_frame` with the instant it acts at, calls
:meth:`Cia402Core.tick` for the drive's own timers (heartbeat, SYNC-loss watchdog) and sends the
synchronous TPDOs it takes from :meth:`Cia402Core.take_tpdos`. Other frames (SDO responses, EMCY,
heartbeat, boot-up) leave at once through ``canopen``.

Behaviour (the firmware's contract):

* NMT: boot-up on power-on and after reset node / reset communication, then PRE-OPERATIONAL;
  start / stop / enter pre-operational. SDO in PRE-OPERATIONAL and OPERATIONAL, PDOs only in
  OPERATIONAL, EMCY not in STOPPED; a SYNC advances the drive's clock in every NMT state (the
  simulated plant runs on whatever the bus does). Reset node restores the whole object dictionary, reset
  communication the 0x1000..0x1FFF area. Leaving OPERATIONAL while OPERATION ENABLED faults the
  drive (EMCY 0x8100).
* SYNC (COB-ID 0x1005, DLC 0 or 1 with the counter; a DLC that does not match 0x1019 sends EMCY
  0x8240 once and still acts): integrate the physics to the SYNC instant with the current active
  since the previous SYNC; RPDO watchdog; sample the encoder; queue the synchronous TPDOs (type
  1..240 every n-th SYNC, 0 when their data changed); then apply the values of the last
  synchronous RPDO received since the previous SYNC; emit the ground truth; automatic transitions.
* RPDO (types 0..240 latched for the next SYNC, 254/255 applied on reception): a frame shorter
  than the mapping is not processed (EMCY 0x8210); a longer one is processed (EMCY 0x8220).
* The power state machine (:mod:`firmware_sim.cia402.power`) from the controlword, by SDO (at
  once) or RPDO. Torque only in OPERATION ENABLED with modes of operation 10 and halt (bit 8)
  clear: ``current_A = clamp(0x6071, +-0x6072) / 1000 * 0x6075 / 1000``, statusword bit 11 while
  clamped; leaving OPERATION ENABLED zeroes the current at once.
* Watchdogs, armed at the first SYNC in OPERATION ENABLED: ``drive.watchdog_periods`` SYNCs in
  a row without an RPDO fault the drive (EMCY 0x8250); ``drive.watchdog_periods`` periods
  without a SYNC fault it (EMCY 0x8100). A fault: zero current, 0x603F, 0x1001, 0x1003, EMCY,
  FAULT; a rising edge of controlword bit 7 clears it (EMCY 0x0000).
* Physics, disturbances and injected faults start at the first entry into OPERATION ENABLED
  (before, the plant rests at its initial state); ``plant.input_delay_samples`` beyond the
  protocol's one period is added to the current path.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import can
import canopen
from canopen import SdoAbortedError

from dob_hil.config import Config
from dob_hil.link.protocol import DriveState
from firmware_sim.actuator import CurrentPath
from firmware_sim.cia402 import objects as ob
from firmware_sim.cia402.node import NMT_RESET_NODE, DriveNetwork, DriveNode
from firmware_sim.cia402.pdo import Layout, PdoLayouts, check_pdo_write
from firmware_sim.cia402.power import (
    CW_HALT,
    SW_FOLLOWS_COMMAND,
    SW_INTERNAL_LIMIT,
    PowerState,
    PowerStateMachine,
)
from firmware_sim.disturbance import Disturbance
from firmware_sim.encoder import Encoder
from firmware_sim.faults import DriveFaults
from firmware_sim.plant import PlantModel, check_single_axis
from firmware_sim.truth import GroundTruth

PROTOCOL_DELAY_SAMPLES = 1  # the RPDO acts at the next SYNC
ERROR_HISTORY_DEPTH = 4  # sub-indices of 0x1003 in the EDS
SDO_RX_BASE = 0x600
_EMCY_DATA = b"\x00" * 5

TruthSink = Callable[[GroundTruth], None]
Objects = Iterable[tuple[tuple[int, int], int]]


@dataclass
class Cia402Stats:
    """Counters of what the drive saw and did."""

    syncs: int = 0
    tpdos_sent: int = 0
    tpdos_lost: int = 0  # dropped by the configured loss (sim.loss_probability)
    rpdos: int = 0
    rpdos_bad: int = 0  # too short: not processed
    sdo_requests: int = 0
    nmt_commands: int = 0
    emcys: int = 0
    frames_ignored: int = 0
    missed_syncs: int = 0  # periods that passed without a SYNC while the watchdog was armed
    missed_rpdos: int = 0  # SYNCs without an RPDO before them while the watchdog was armed


def _encoder_ratio(counts_per_unit: float) -> tuple[int, int]:
    """0x608F (increments, revolutions) for the configured counts per unit."""
    for revs in (1, 10, 100, 1000):
        n = counts_per_unit * revs
        if abs(n - round(n)) < 1e-9 * max(1.0, n):
            return round(n), revs
    return round(counts_per_unit), 1


class Cia402Core:
    def __init__(self, bus: can.BusABC, config: Config, *, lockstep: bool, want_truth: bool) -> None:
        check_single_axis(config.plant)
        drive, sim, plant = config.drive, config.sim, config.plant
        self.lockstep = lockstep
        self.want_truth = want_truth
        self.node_id = drive.node_id
        self.sdo_rx_id = SDO_RX_BASE + drive.node_id
        self.watchdog_periods = drive.watchdog_periods
        self.plant_period_ns = plant.period_ns
        extra = max(0, plant.input_delay_samples - PROTOCOL_DELAY_SAMPLES)
        self.extra_delay_ns = extra * plant.period_ns
        self.disturbance = Disturbance(sim.disturbances, plant.period_s / sim.substeps)
        self.plant = PlantModel(plant, sim.substeps, self.disturbance, sim.initial_state)
        self.encoder = Encoder(
            drive.encoder_counts_per_unit, drive.encoder_bits, sim.noise_counts_std, sim.seed
        )
        self.path = CurrentPath()
        self.faults = DriveFaults.from_config(config)
        self.power = PowerStateMachine()
        self.stats = Cia402Stats()
        od = canopen.import_od(str(ob.shipped_eds()), drive.node_id)
        self.network = DriveNetwork(bus)
        self.node = DriveNode(drive.node_id, od)
        self.network.add_node(self.node)
        self.node.nmt.on_reset = self._on_nmt_reset
        self.node.on_read(self._on_read)
        self.node.on_write(self._on_write)
        self.layouts = PdoLayouts(self.node)
        self._factory = {
            (ob.RATED_CURRENT, 0): round(drive.dac_lsb_A * 1e6),
            (ob.ENCODER_RESOLUTION, 1): _encoder_ratio(drive.encoder_counts_per_unit)[0],
            (ob.ENCODER_RESOLUTION, 2): _encoder_ratio(drive.encoder_counts_per_unit)[1],
        }
        # --- clock ---
        self.time_ns = 0  # the drive's clock: the physics is integrated up to here
        self.origin_ns: int | None = None  # plant time zero: the first OPERATION ENABLED
        self.period_index = 0
        self._first_sync_ns: int | None = None
        self._clock_started = False
        self._last_sync_ns = 0
        self._next_heartbeat_ns: int | None = None
        # --- application state ---
        self.mode = ob.MODE_NONE
        self.target_torque = 0  # per mille of rated torque, as received
        self.counts = 0  # position actual value (increments)
        self.velocity = 0  # increments per second
        self.saturated = False
        self.error_code = 0
        self.error_register = 0
        self.error_history: list[int] = []
        self._pending: dict[tuple[int, int], int] = {}  # synchronous RPDO values for the next SYNC
        self._rpdo_since_sync = False
        self._watch_armed = False
        self._missed_rpdo = 0
        self._missed_sync = 0
        self._sync_length_reported = False
        self._tpdo_syncs: list[int] = []
        self._tpdo_last: list[bytes | None] = []
        self._tpdos: list[tuple[int, bytes]] = []
        self._truth: GroundTruth | None = None
        self._sample_t_ns: int | None = None
        self._now_ns = 0  # arrival of the SDO request being served
        self._load_settings()

    # --- settings cached from the object dictionary ------------------------------------------------
    def _raw(self, index: int, subindex: int = 0) -> int:
        obj = self.node.object_dictionary.get_variable(index, subindex)
        assert obj is not None
        value = obj.decode_raw(self.node.get_data(index, subindex))
        assert isinstance(value, int)
        return value

    def _load_settings(self) -> None:
        for (index, subindex), value in self._factory.items():
            obj = self.node.object_dictionary.get_variable(index, subindex)
            assert obj is not None
            self.node.data_store.setdefault(index, {})[subindex] = obj.encode_raw(value)
        self.rated_current_mA = self._raw(ob.RATED_CURRENT)
        self.max_torque = self._raw(ob.MAX_TORQUE)
        self.power.quick_stop_option = self._raw(ob.QUICK_STOP_OPTION)
        cycle_us = self._raw(ob.CYCLE_PERIOD)
        self.period_ns = self._cycle_ns(cycle_us)
        self.sync_cob_id = self._raw(ob.COB_ID_SYNC) & 0x7FF
        self.sync_overflow = self._raw(ob.SYNC_OVERFLOW)
        emcy = self._raw(ob.COB_ID_EMCY)
        self.node.emcy.cob_id = emcy & 0x7FF
        self.emcy_enabled = not emcy & ob.PDO_INVALID
        self.layouts.stale = True

    def _cycle_ns(self, cycle_us: int) -> int:
        """The SYNC period from 0x1006: the plant's period when 0x1006 is 0 or that period in whole us."""
        if not cycle_us or abs(cycle_us * 1000 - self.plant_period_ns) < 1000:
            return self.plant_period_ns
        return cycle_us * 1000

    # --- power-on and NMT ---------------------------------------------------------------------------
    def power_on(self) -> None:
        """Initialisation done: boot-up message, PRE-OPERATIONAL, SWITCH ON DISABLED."""
        self.power.boot()
        self.node.nmt.boot()

    def _on_nmt_reset(self, command: int) -> None:
        was_enabled = self.power.state is PowerState.OPERATION_ENABLED
        if command == NMT_RESET_NODE:
            self.node.data_store.clear()
            self._cut(self.time_ns)
            self.mode = ob.MODE_NONE
            self.target_torque = 0
            self._pending.clear()
            self.error_code = self.error_register = 0
            self.error_history.clear()
            self.power.boot()
        else:
            for index in [i for i in self.node.data_store if i < 0x2000]:
                del self.node.data_store[index]
            if was_enabled:
                self._fault(ob.EMCY_COMMUNICATION, self.time_ns)
        self._load_settings()
        self.node.nmt.boot()
        self._tpdo_syncs, self._tpdo_last = [], []

    def _on_nmt(self, data: bytes, t_ns: int) -> None:
        before = self.node.nmt.state
        self.network.notify(0, bytearray(data), t_ns * 1e-9)
        after = self.node.nmt.state
        if before == "OPERATIONAL" and after != "OPERATIONAL" and self.power.torque_allowed:
            self._fault(ob.EMCY_COMMUNICATION, t_ns)
        if after == "OPERATIONAL" and before != "OPERATIONAL":
            self._tpdo_syncs, self._tpdo_last = [], []

    # --- frames -------------------------------------------------------------------------------------
    def on_frame(self, can_id: int, data: bytes, now_ns: int) -> None:
        """Act on one received (standard, data) frame; ``now_ns`` is when it arrived (drive clock)."""
        if can_id == 0:
            if len(data) == 2:
                self.stats.nmt_commands += 1
                self._on_nmt(data, now_ns)
                return
        elif can_id == self.sync_cob_id:
            self._on_sync(data, now_ns)
            return
        elif can_id == SDO_RX_BASE + self.node_id:
            if len(data) == 8 and self.node.nmt.state != "STOPPED":
                self.stats.sdo_requests += 1
                self._now_ns = now_ns
                self._on_sdo(data, now_ns)
                return
        elif self.node.nmt.state == "OPERATIONAL":
            self.layouts.refresh()
            layout = self.layouts.rpdos.get(can_id)
            if layout is not None:
                self._on_rpdo(layout, data, now_ns)
                return
        self.stats.frames_ignored += 1

    def _on_sdo(self, data: bytes, now_ns: int) -> None:
        """canopen's SDO server answers; what it cannot (it raises) is aborted here, not fatal."""
        if data[0] & 0xE0 == 0xE0:  # command specifier 7 does not exist
            self._sdo_abort(data, ob.ABORT_INVALID_COMMAND)
            return
        try:
            self.network.notify(SDO_RX_BASE + self.node_id, bytearray(data), now_ns * 1e-9)
        except (struct.error, TypeError):  # e.g. a segment request with no transfer in progress
            self._sdo_abort(data, ob.ABORT_INVALID_COMMAND)

    def _sdo_abort(self, request: bytes, code: int) -> None:
        payload = bytes([0x80]) + request[1:4] + code.to_bytes(4, "little")
        self.network.send_message(0x580 + self.node_id, payload)

    def _on_rpdo(self, layout: Layout, data: bytes, now_ns: int) -> None:
        if len(data) < layout.size:
            self.stats.rpdos_bad += 1
            self._emcy(ob.EMCY_PDO_LENGTH, self.error_register)
            return
        if len(data) > layout.size:
            self._emcy(ob.EMCY_PDO_LENGTH_EXCEEDED, self.error_register)
        self.stats.rpdos += 1
        self._rpdo_since_sync = True
        values = layout.packer.unpack_from(data)
        if layout.trans_type <= 240:
            self._pending.update(zip(layout.objects, values, strict=True))
        else:
            self._apply(zip(layout.objects, values, strict=True), now_ns)

    def _apply(self, items: Objects, t_ns: int) -> None:
        """Take received object values (an RPDO): controlword last, the current updated."""
        controlword: int | None = None
        for (index, subindex), value in items:
            if index == ob.CONTROLWORD:
                controlword = value
            elif index == ob.TARGET_TORQUE:
                self.target_torque = value
            elif index == ob.MODES_OF_OPERATION:
                if value in ob.SUPPORTED_MODES:
                    self.mode = value
            else:
                obj = self.node.object_dictionary.get_variable(index, subindex)
                if obj is not None:
                    self.node.data_store.setdefault(index, {})[subindex] = obj.encode_raw(value)
        if controlword is not None:
            self._controlword(controlword, t_ns)
        else:
            self._update_current(t_ns)

    # --- SYNC ---------------------------------------------------------------------------------------
    def _sync_instant(self, now_ns: int) -> int:
        if not self.lockstep:
            return max(now_ns, self.time_ns)
        if not self._clock_started:
            self._clock_started = True
            return self.time_ns
        return self.time_ns + self.period_ns

    def _on_sync(self, data: bytes, now_ns: int) -> None:
        if len(data) > 1:
            self._emcy(ob.EMCY_SYNC_LENGTH, self.error_register)
            self.stats.frames_ignored += 1
            return
        if (len(data) == 1) != (self.sync_overflow > 0) and not self._sync_length_reported:
            self._sync_length_reported = True
            self._emcy(ob.EMCY_SYNC_LENGTH, self.error_register)
        counter = data[0] if data else None
        t = self._sync_instant(now_ns)
        self.stats.syncs += 1
        self._integrate_to(t)
        self._set_period_index(t)
        self.power.on_sync()
        self._last_sync_ns = t
        self._missed_sync = 0
        self._injected_faults()
        self._sync_tail(t, counter)

    def _sync_tail(self, t: int, counter: int | None) -> None:
        """A SYNC at ``t`` once the physics is there: RPDO watchdog, sample, TPDOs, pending values,
        truth, heartbeat."""
        if self._watch_armed and self.power.torque_allowed:
            if self._rpdo_since_sync:
                self._missed_rpdo = 0
            else:
                self._missed_rpdo += 1
                self.stats.missed_rpdos += 1
                if self._missed_rpdo >= self.watchdog_periods:
                    self._fault(ob.EMCY_RPDO_TIMEOUT, t)
        held_A = self.path.held_A
        self._sample(t)
        if self.node.nmt.state == "OPERATIONAL":
            self._queue_tpdos(counter)
        if self._pending:
            pending, self._pending = self._pending, {}
            self._apply(pending.items(), t)
        else:
            self._update_current(t)
        self._rpdo_since_sync = False
        self._watch_armed = self.power.torque_allowed
        if self.want_truth:
            self._truth = self._ground_truth(t, held_A)
        self._heartbeat(t)

    def _set_period_index(self, t_ns: int) -> None:
        if self.lockstep:
            self.period_index = t_ns // self.period_ns
            return
        if self._first_sync_ns is None:
            self._first_sync_ns = t_ns
            self.period_index = 0
            return
        k = round((t_ns - self._first_sync_ns) / self.period_ns)
        self.period_index = max(self.period_index + 1, k)

    def advance_period(self) -> None:
        """Lockstep: one period passes without a SYNC (the SYNC-loss watchdog counts it)."""
        self._clock_started = True
        t = self.time_ns + self.period_ns
        self._integrate_to(t)
        self.period_index = t // self.period_ns
        held_A = self.path.held_A
        self._count_missed_sync(t)
        if self.want_truth:
            self._truth = self._ground_truth(t, held_A)
        self._heartbeat(t)

    def _count_missed_sync(self, t_ns: int) -> None:
        if self._watch_armed and self.power.torque_allowed:
            self._missed_sync += 1
            self.stats.missed_syncs += 1
            if self._missed_sync >= self.watchdog_periods:
                self._fault(ob.EMCY_COMMUNICATION, t_ns)

    def tick(self, now_ns: int) -> None:
        """Real time: the drive's own timers at ``now_ns`` (SYNC-loss watchdog, heartbeat)."""
        if self._watch_armed and self.power.torque_allowed:
            deadline = self._last_sync_ns + (self._missed_sync + 1) * self.period_ns
            while now_ns >= deadline and self.power.torque_allowed:
                self._integrate_to(deadline)
                self._count_missed_sync(deadline)
                deadline += self.period_ns
        self._heartbeat(now_ns)

    def next_timer_ns(self) -> int | None:
        """Real time: when :meth:`tick` next has something to do (None: nothing scheduled)."""
        times = []
        if self._watch_armed and self.power.torque_allowed:
            times.append(self._last_sync_ns + (self._missed_sync + 1) * self.period_ns)
        if self._next_heartbeat_ns is not None and self.node.nmt.heartbeat_ms:
            times.append(self._next_heartbeat_ns)
        return min(times) if times else None

    def _injected_faults(self) -> None:
        f = self.faults
        if f is None or f.origin is None:
            return
        k = self.period_index - f.origin
        if f.fault_period is not None and not f.fault_injected and k >= f.fault_period:
            f.fault_injected = True
            self._fault(ob.EMCY_OVERCURRENT, self.time_ns)
        if f.silent_period is not None and k >= f.silent_period:
            f.silent = True
            self.network.muted = True

    # --- sampling and TPDOs -------------------------------------------------------------------------
    def _sample(self, t_ns: int) -> None:
        try:
            counts = self.encoder.read(self.plant.position())
        except ValueError:
            self._fault(ob.EMCY_ENCODER, t_ns)
            counts = self.counts
        if self.faults is not None:
            counts = self.faults.counts(self.period_index, counts)
        if self._sample_t_ns is not None and t_ns > self._sample_t_ns:
            step = ((counts - self.counts + 2**31) % 2**32) - 2**31  # int32 wrap-around
            v = round(
                step * 1e9 / (t_ns - self._sample_t_ns)
            )  # clamped to int32 (if-chain: no min/max calls)
            self.velocity = -(2**31) if v < -(2**31) else 2**31 - 1 if v > 2**31 - 1 else v
        self._sample_t_ns = t_ns
        self.counts = counts

    @property
    def statusword(self) -> int:
        sw = self.power.statusword_bits
        if self.power.torque_allowed:
            if self.mode == ob.MODE_CST and not self.power.controlword & CW_HALT:
                sw |= SW_FOLLOWS_COMMAND
            if self.saturated:
                sw |= SW_INTERNAL_LIMIT
        return sw

    def _torque_actual(self) -> int:
        return round(self.path.held_A * 1e6 / self.rated_current_mA) if self.rated_current_mA else 0

    def _value(self, index: int, subindex: int) -> int:
        live = self._live(index, subindex)
        return live if live is not None else self._raw(index, subindex)

    def _live(self, index: int, subindex: int) -> int | None:
        if index == ob.STATUSWORD:
            return self.statusword
        if index == ob.POSITION_ACTUAL:
            return self.counts
        if index == ob.VELOCITY_ACTUAL:
            return self.velocity
        if index == ob.CONTROLWORD:
            return self.power.controlword
        if index in (ob.MODES_OF_OPERATION, ob.MODES_DISPLAY):
            return self.mode
        if index == ob.TARGET_TORQUE:
            return self.target_torque
        if index in (ob.TORQUE_ACTUAL, ob.CURRENT_ACTUAL):
            return self._torque_actual()
        if index == ob.ERROR_CODE:
            return self.error_code
        if index == ob.ERROR_REGISTER:
            return self.error_register
        if index == ob.ERROR_HISTORY:
            if subindex == 0:
                return len(self.error_history)
            return self.error_history[subindex - 1] if subindex <= len(self.error_history) else 0
        return None

    def _queue_tpdos(self, counter: int | None) -> None:
        self.layouts.refresh()
        tpdos = self.layouts.tpdos
        if len(self._tpdo_syncs) != len(tpdos):
            self._tpdo_syncs = [0] * len(tpdos)
            self._tpdo_last = [None] * len(tpdos)
        for i, lay in enumerate(tpdos):
            waiting = lay.sync_start and counter is not None and self._tpdo_syncs[i] == 0
            if waiting and counter != lay.sync_start:
                continue  # transmission starts at the SYNC whose counter is the start value
            self._tpdo_syncs[i] += 1
            payload = lay.packer.pack(*[self._value(idx, sub) for idx, sub in lay.objects])
            if lay.trans_type == 0:
                if payload == self._tpdo_last[i]:
                    continue
            elif self._tpdo_syncs[i] % lay.trans_type:
                continue
            self._tpdo_last[i] = payload
            self._tpdos.append((lay.cob_id, payload))

    def take_rpdo(self, layout: Layout, values: tuple[int, ...], count: int) -> None:
        """``count`` synchronous RPDOs of ``layout`` received, the last carrying ``values`` (what
        :meth:`on_frame` does for each, the lockstep fast path's deferred share)."""
        self.stats.rpdos += count
        self._rpdo_since_sync = True
        self._pending.update(zip(layout.objects, values, strict=True))

    def take_tpdos(self) -> list[tuple[int, bytes]]:
        out, self._tpdos = self._tpdos, []
        return out

    def take_truth(self) -> GroundTruth | None:
        truth, self._truth = self._truth, None
        return truth

    def _ground_truth(self, t_ns: int, held_A: float) -> GroundTruth:
        tau = None if self.origin_ns is None else t_ns - self.origin_ns
        w = 0.0 if tau is None else self.disturbance.value_A(tau * 1e-9)
        # without NamedTuple's Python-level __new__ (the per-period path)
        return tuple.__new__(
            GroundTruth, (self.period_index, t_ns, self.plant.state, w, held_A, self.drive_state)
        )

    @property
    def drive_state(self) -> DriveState:
        s = self.power.state
        if s is PowerState.OPERATION_ENABLED:
            return DriveState.ENABLED
        if s in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE):
            return DriveState.FAULT
        return DriveState.DISABLED

    # --- heartbeat and EMCY -------------------------------------------------------------------------
    def _heartbeat(self, t_ns: int) -> None:
        nmt = self.node.nmt
        if nmt.heartbeat_changed:
            nmt.heartbeat_changed = False
            self._next_heartbeat_ns = t_ns + nmt.heartbeat_ms * 1_000_000 if nmt.heartbeat_ms else None
        if self._next_heartbeat_ns is None or t_ns < self._next_heartbeat_ns:
            return
        self.network.send_message(0x700 + self.node_id, bytes([nmt.state_code]))
        period_ns = nmt.heartbeat_ms * 1_000_000
        while self._next_heartbeat_ns <= t_ns:
            self._next_heartbeat_ns += period_ns

    def _emcy(self, code: int, register: int) -> None:
        if not self.emcy_enabled or self.node.nmt.state not in ("PRE-OPERATIONAL", "OPERATIONAL"):
            return
        self.stats.emcys += 1
        self.node.emcy.send(code, register, _EMCY_DATA)

    # --- power state and current --------------------------------------------------------------------
    def _controlword(self, controlword: int, t_ns: int) -> None:
        self._integrate_to(t_ns)  # the old state's current up to now (and the plant origin after)
        before = self.power.state
        after = self.power.apply(controlword)
        if before is PowerState.FAULT and after is not PowerState.FAULT:
            self.error_code = self.error_register = 0
            self._emcy(ob.EMCY_NO_ERROR, 0)
        if after is PowerState.OPERATION_ENABLED and before is not PowerState.OPERATION_ENABLED:
            self._watch_armed = False
            self._missed_rpdo = self._missed_sync = 0
            if self.origin_ns is None:
                self.origin_ns = t_ns
            if self.faults is not None:
                self.faults.on_enabled(self.period_index)
        self._update_current(t_ns)

    def _update_current(self, t_ns: int) -> None:
        if not self.power.torque_allowed:
            if self.path.held_A != 0.0 or self.path.pending:
                self._cut(t_ns)
            self.saturated = False
            return
        torque = self.target_torque
        if self.mode != ob.MODE_CST or self.power.controlword & CW_HALT:
            torque = 0
        limit = self.max_torque
        clamped = -limit if torque < -limit else limit if torque > limit else torque
        self.saturated = clamped != torque
        current_A = clamped * self.rated_current_mA * 1e-6
        assert self.origin_ns is not None
        self._integrate_to(t_ns)
        self.path.schedule(t_ns - self.origin_ns + self.extra_delay_ns, current_A)

    def _cut(self, t_ns: int) -> None:
        self._integrate_to(t_ns)
        if self.origin_ns is not None:
            self.path.cut(t_ns - self.origin_ns)
        self.saturated = False

    def _fault(self, code: int, t_ns: int) -> None:
        if not self.power.fault():
            return
        self._cut(t_ns)
        self.error_code = code
        self.error_register = ob.FAULT_REGISTER.get(code, ob.ER_GENERIC)
        self.error_history.insert(0, code)
        del self.error_history[ERROR_HISTORY_DEPTH:]
        self._emcy(code, self.error_register)
        self.power.fault_reaction_done()

    # --- physics ------------------------------------------------------------------------------------
    def _integrate_to(self, t_ns: int) -> None:
        """Advance the physics to ``t_ns`` (drive clock), switching the current where changes fall due."""
        if t_ns <= self.time_ns:
            return
        if self.origin_ns is None:
            self.time_ns = t_ns
            return
        path, plant = self.path, self.plant
        tau, end_tau = self.time_ns - self.origin_ns, t_ns - self.origin_ns
        while tau < end_tau:
            path.apply_due(tau)
            nxt = path.next_change_ns()
            end = end_tau if nxt is None or nxt > end_tau else nxt
            plant.advance(tau, end, path.held_A)
            tau = end
        self.time_ns = t_ns

    # --- object dictionary callbacks (SDO) ----------------------------------------------------------
    def _on_read(self, index: int, subindex: int, od: canopen.objectdictionary.ODVariable) -> int | None:
        return self._live(index, subindex)

    def _on_write(
        self, index: int, subindex: int, od: canopen.objectdictionary.ODVariable, data: bytes
    ) -> None:
        value = od.decode_raw(data)
        if not isinstance(value, int):
            return
        if check_pdo_write(self.node, index, subindex, value):
            self.layouts.stale = True
            return
        t = max(self._now_ns, self.time_ns)
        if index == ob.CONTROLWORD:
            self._controlword(value, t)
        elif index == ob.MODES_OF_OPERATION:
            if value not in ob.SUPPORTED_MODES:
                raise SdoAbortedError(ob.ABORT_INVALID_VALUE)
            self.mode = value
            self._update_current(t)
        elif index == ob.TARGET_TORQUE:
            self._pending[(ob.TARGET_TORQUE, 0)] = value  # a cyclic synchronous setpoint: next SYNC
        elif index == ob.ERROR_HISTORY:
            if value != 0:
                raise SdoAbortedError(ob.ABORT_INVALID_VALUE)
            self.error_history.clear()
        elif index == ob.QUICK_STOP_OPTION:
            if not 0 <= value <= 8:
                raise SdoAbortedError(ob.ABORT_INVALID_VALUE)
            self.power.quick_stop_option = value
        elif index == ob.RATED_CURRENT:
            if value == 0:
                raise SdoAbortedError(ob.ABORT_INVALID_VALUE)
            self.rated_current_mA = value
        elif index == ob.MAX_TORQUE:
            self.max_torque = value
        elif index == ob.ENCODER_RESOLUTION:
            if value != self._factory[(index, subindex)]:
                raise SdoAbortedError(ob.ABORT_INVALID_VALUE)  # the fitted encoder's resolution
        elif index == ob.CYCLE_PERIOD:
            self.period_ns = self._cycle_ns(value)
        elif index == ob.COB_ID_SYNC:
            if value & (ob.PDO_NO_RTR | ob.PDO_EXTENDED):  # bit 30: we cannot produce SYNC
                raise SdoAbortedError(ob.ABORT_INVALID_VALUE)
            self.sync_cob_id = value & 0x7FF
        elif index == ob.SYNC_OVERFLOW:
            if value == 1 or value > 240:
                raise SdoAbortedError(ob.ABORT_INVALID_VALUE)
            self.sync_overflow = value
            self._sync_length_reported = False
        elif index == ob.COB_ID_EMCY:
            if value & ob.PDO_EXTENDED:
                raise SdoAbortedError(ob.ABORT_INVALID_VALUE)
            self.node.emcy.cob_id = value & 0x7FF
            self.emcy_enabled = not value & ob.PDO_INVALID
