"""The CiA 402 host link: configuration over SDO (``canopen``), then SYNC / TPDO / RPDO by hand.

One drive (``drive.node_id``), one axis, cyclic synchronous torque (mode 10).

Configuration (:meth:`Cia402DriveLink.enable` / :meth:`~Cia402DriveLink.enable_lockstep`), with the
``canopen`` library's SDO client and PDO maps on a :class:`canopen.RemoteNode` built from the EDS
(``[drive.cia402] eds``): NMT pre-operational; device type 0x1000 (must be CiA 402) and identity
0x1018; supported modes 0x6502 (bit 9, CST) where the EDS has it; the scaling objects 0x6075 rated
current, 0x6076 rated torque, 0x6072 max torque and 0x608F position encoder resolution, refused
(:class:`~dob_hil.errors.ConfigError` naming the object) when the config contradicts them; modes of
operation 0x6060 = 10, checked in 0x6061; RPDO1 = 0x6040 + 0x6071 and TPDO1 = 0x6041 + 0x6064
(TPDO2 = 0x606C with ``map_velocity``), transmission type 1, saved with canopen's disable / map /
enable sequence, every other PDO disabled; 0x1006 communication cycle period; 0x1019 SYNC counter
overflow (``sync_counter``); 0x1017 heartbeat producer time; NMT start. Then the power state machine
through the controlword over SDO (0x6040 written, 0x6041 read: no SYNC needed): fault reset on a
rising edge of bit 7, shutdown, switch on, enable operation, until OPERATION_ENABLED or the
timeout, which names the state the drive is stuck in and its error code 0x603F.

During configuration in real time a short-lived pump thread reads the bus and feeds ``canopen``
(whose SDO client blocks for its answers). In lockstep every frame sent while configuring is
followed, in the same thread, by the drive's ``service()`` and the frames it answers with, so each
SDO answer is waiting before ``canopen`` asks for it: no thread, and the same frames in the same
order every run. The cyclic phase is single-threaded: the runner calls
:meth:`send_trigger` (SYNC), :meth:`receive_feedback`, :meth:`quantize` and :meth:`send_command`
(:class:`dob_hil.loop.host_clocked.HostClockedLink`).

Cyclic frames are packed directly with the layout mapped above (:mod:`dob_hil.link.cia402.codec`).
A TPDO1 is accepted only as the answer to the last SYNC sent; a second one, or one still queued
when the next SYNC goes out, is stale (STALE_FEEDBACK). ``Feedback.seq`` is the sample counter
(SYNCs sent - 1) mod 256. EMCY frames give DRIVE_FAULT events with code and register (code 0x0000:
a DRIVE_STATE event "error reset"); heartbeats that change the NMT state give DRIVE_STATE events.

Units: the command is the target torque 0x6071 in per mille of rated torque; as the drive's
current is proportional to its torque, 1 per mille = rated current 0x6075 / 1000, which must equal
``drive.dac_lsb_A``, and the code is clamped at ``floor(current_limit_A / dac_lsb_A)`` (the native
:class:`~dob_hil.link.native.DacQuantizer`). The position 0x6064 is in increments, unwrapped over
the i32 (``drive.encoder_bits``) and divided by ``drive.encoder_counts_per_unit``, which must equal
0x608F increments / revolutions.

Safe stop (:meth:`safe_stop`, every exit path): RPDO zero torque with the drive still enabled, SYNC;
RPDO disable operation, SYNC; RPDO shutdown, SYNC; NMT enter pre-operational. The SYNCs stop only
after that (a real-time caller spaces them by one period).
"""

from __future__ import annotations

import functools
import logging
import math
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any, Final

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from dob_hil.config import Config
from dob_hil.errors import ConfigError, DobHilError, DriveFault, ProtocolError
from dob_hil.link.base import EventHook, Feedback, FrameHook, LinkEvent, LinkEventKind
from dob_hil.link.cia402 import codec
from dob_hil.link.cia402.codec import Command, Emcy, NmtCommand, NmtState, PowerState
from dob_hil.link.cia402.options import Cia402Options, options_of
from dob_hil.link.closing import ClosingLink
from dob_hil.link.message import data_frame
from dob_hil.link.native import DacQuantizer
from dob_hil.link.unwrap import CountUnwrapper

_log = logging.getLogger(__name__)

N_AXES: Final = 1
MAX_READS_AFTER_DEADLINE: Final = 1024
SETTLE_ROUNDS: Final = 16  # lockstep configuration: drive services per frame sent, at most
LOCKSTEP_STATE_TIMEOUT_NS: Final = 5_000_000_000  # wall clock; the embedded drive answers at once
STATE_POLL_S: Final = 0.002
_TPDO1: Final = codec.TPDO1
_TPDO1_SIZE: Final = _TPDO1.size
_TPDO1_UNPACK: Final = _TPDO1.unpack
_RPDO1: Final = codec.RPDO1
_OPERATION_ENABLED: Final = PowerState.OPERATION_ENABLED
_FAULT: Final = PowerState.FAULT  # (identity tests: an Enum's hash is a Python-level call)
_FAULT_REACTION: Final = PowerState.FAULT_REACTION_ACTIVE
_INTERNAL_LIMIT: Final = codec.SW_INTERNAL_LIMIT
_SW_FAULT: Final = codec.SW_FAULT


@dataclass(slots=True)
class Cia402Stats:
    rx_frames: int = 0
    feedback: int = 0
    missed_feedback: int = 0  # SYNCs whose TPDO1 never came
    stale_feedback: int = 0
    malformed_frames: int = 0
    foreign_frames: int = 0
    error_frames: int = 0
    own_echoes: int = 0
    emcy: int = 0
    encoder_jumps: int = 0
    syncs: int = 0
    tx_frames: int = 0
    send_failures: int = 0
    clamped_commands: int = 0
    nonfinite_currents: int = 0


@dataclass(frozen=True)
class DriveIdentity:
    device_type: int
    vendor_id: int | None
    product_code: int | None
    revision: int | None
    serial: int | None
    rated_current_mA: int
    rated_torque_mNm: int
    max_torque_permille: int
    encoder_increments: int
    encoder_revolutions: int


class _HookedNetwork(canopen.Network):
    """canopen's network with our bus, every frame it sends also handed to ``on_send``; then
    ``after_send()``, if set (lockstep: the drive's answer taken at once)."""

    def __init__(self, bus: can.BusABC, on_send: Callable[[can.Message], None]) -> None:
        super().__init__(bus)
        self._on_send = on_send
        self.after_send: Callable[[], object] | None = None

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        msg = can.Message(arbitration_id=can_id, is_extended_id=can_id > 0x7FF, data=data,
                          is_remote_frame=remote)  # fmt: skip
        bus = self.bus
        assert bus is not None
        with self.send_lock:
            bus.send(msg)
        self._on_send(msg)
        if self.after_send is not None:
            self.after_send()


class Cia402DriveLink(ClosingLink):
    """One CiA 402 drive in cyclic synchronous torque on a python-can bus. See the module docstring."""

    n_axes: Final = N_AXES

    def __init__(
        self,
        bus: can.BusABC,
        config: Config,
        *,
        frame_hook: FrameHook | None = None,
        event_hook: EventHook | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        owns_bus: bool = False,
        max_counts_step: int | None = None,
    ) -> None:
        drive = config.drive
        if drive.profile != "cia402":
            raise ConfigError(
                "drive.profile", f"Cia402DriveLink drives the cia402 profile, got {drive.profile!r}"
            )
        try:
            self._ids = codec.cob_ids(drive.node_id)
        except ProtocolError as exc:
            raise ConfigError("drive.node_id", str(exc)) from None
        self._quantizer = DacQuantizer(drive, on_nonfinite=self._nonfinite_current)
        self.quantize = self._quantizer.quantize  # type: ignore[method-assign]  # (see quantize)
        self._limit_code = self._quantizer.limit_code
        self._options: Cia402Options = options_of(drive.options)
        self._config = config
        self._drive = drive
        self._node = drive.node_id
        self._period_ns = config.plant.period_ns
        self._bus = bus
        self._frame_hook = frame_hook
        self._event_hook = event_hook
        self._clock_ns = clock_ns
        self._owns_bus = owns_bus
        self._counts_per_unit = drive.encoder_counts_per_unit
        self._unwrapper = CountUnwrapper(drive.encoder_bits)
        self._max_counts_step = 2 ** (drive.encoder_bits - 2) if max_counts_step is None else max_counts_step
        ids = self._ids
        self._tpdo1_id = ids["TPDO1"]
        self._rpdo1_id = ids["RPDO1"]
        self._handlers: dict[int, Callable[[can.Message, int], Feedback | None]] = {
            ids["TPDO1"]: self._on_tpdo1,
            ids["TPDO2"]: self._on_tpdo2,
            ids["EMCY"]: self._on_emcy,
            ids["HEARTBEAT"]: self._on_heartbeat,
            ids["SDO_TX"]: self._on_sdo_answer,
        }
        self._own_tx_ids = frozenset((codec.NMT_ID, codec.SYNC_ID, ids["RPDO1"], ids["SDO_RX"]))
        self._lock = threading.RLock()  # the real-time pump thread against the caller's; held in lockstep too
        self._configuring = False  # SDO answers are expected (enable, until the cyclic phase)
        self._network: _HookedNetwork | None = None
        self._pump: threading.Thread | None = None
        self._pump_stop = threading.Event()
        self._pump_error: BaseException | None = None
        self._lockstep = False
        self._started = False  # NMT start was sent: safe_stop has something to stop
        self._closed = False
        self._controlword = Command.SHUTDOWN.word  # what the RPDO carries
        self._awaiting_tpdo = False
        self._sync_counter = 0
        self._sync_msg = can.Message(0.0, codec.SYNC_ID, False, False, False, None, None, b"")
        self._state: PowerState | None = None
        self._statusword: int | None = None
        self._nmt_state: NmtState | None = None
        self._last_emcy: Emcy | None = None
        self._velocity: int | None = None
        self.identity: DriveIdentity | None = None
        self.stats = Cia402Stats()

    # --- properties ------------------------------------------------------------------------------
    @property
    def current_limit_A(self) -> float:
        return self._drive.current_limit_A

    @property
    def limit_code(self) -> int:
        """The largest |target torque| in per mille ever sent."""
        return self._limit_code

    @property
    def node_id(self) -> int:
        return self._node

    @property
    def power_state(self) -> PowerState | None:
        return self._state

    @property
    def last_emcy(self) -> Emcy | None:
        return self._last_emcy

    @property
    def velocity_counts_per_s(self) -> int | None:
        """The last velocity actual value 0x606C (TPDO2, with ``map_velocity``)."""
        return self._velocity

    @property
    def closed(self) -> bool:
        return self._closed

    # --- configuration and enabling ------------------------------------------------------------------
    def enable(self, timeout_ns: int) -> None:
        """Configure the drive and bring it to OPERATION_ENABLED (a drive on its own clock)."""
        self._configure_and_enable(None, timeout_ns)

    def enable_lockstep(self, service: Callable[[], int], max_rounds: int = 3) -> None:
        """The same against the embedded lockstep drive: ``service()`` runs after every frame sent
        while configuring (the drive acts only when serviced), never after this returns."""
        self._lockstep = True
        self._configure_and_enable(service, LOCKSTEP_STATE_TIMEOUT_NS)

    def _configure_and_enable(self, service: Callable[[], int] | None, timeout_ns: int) -> None:
        self._check_open()
        network = _HookedNetwork(self._bus, self._on_config_tx)
        try:
            node = canopen.RemoteNode(self._node, _object_dictionary(self._options.eds_path, self._node))
        except Exception as exc:
            raise ConfigError(
                "drive.cia402.eds", f"{self._options.eds_path}: not a readable EDS/DCF: {exc}"
            ) from None
        node.sdo.RESPONSE_TIMEOUT = self._options.sdo_timeout_s
        network.add_node(node)
        self._network = network
        if service is not None:
            # lockstep: the drive acts only when serviced, so every frame sent while configuring is
            # answered in this thread, before canopen waits for the answer: no pump thread, no
            # thread hand-over per SDO, the same frames in the same order every run (the enable
            # takes about 2 ms instead of 3-8)
            network.after_send = functools.partial(self._settle_config, network, service)
        self._configuring = True  # until the pump has stopped: SDO answers are expected
        try:
            if network.after_send is not None:
                network.after_send()  # what the drive sent before (its boot-up) comes first
            else:
                self._start_pump(network)
            self._configure(node)
            self._power_up(node, timeout_ns)
        finally:
            network.after_send = None
            self._stop_pump()
            self._configuring = False
        self._awaiting_tpdo = False

    def _configure(self, node: Any) -> None:
        self._nmt(NmtCommand.ENTER_PRE_OPERATIONAL)
        device_type = self._read(node, 0x1000)
        if device_type & 0xFFFF != codec.DEVICE_PROFILE_402:
            raise ConfigError(
                "drive.profile",
                f"node {self._node} is no CiA 402 device: device type 0x1000 = 0x{device_type:08X} "
                f"(profile {device_type & 0xFFFF}, expected 402)",
            )
        vendor, product, revision, serial = (
            self._read(node, 0x1018, sub) if self._has(node, 0x1018, sub) else None for sub in (1, 2, 3, 4)
        )
        if self._has(node, 0x6502):
            modes = self._read(node, 0x6502)
            if not modes & codec.SUPPORTED_MODE_CST_BIT:
                raise ConfigError(
                    "drive.profile",
                    f"node {self._node} does not support cyclic synchronous torque: supported drive "
                    f"modes 0x6502 = 0x{modes:08X} (bit 9 clear)",
                )
        rated_current_mA = self._read(node, 0x6075)
        rated_torque_mNm = self._read(node, 0x6076)
        max_torque = self._read(node, 0x6072)
        increments = self._read(node, 0x608F, 1)
        revolutions = self._read(node, 0x608F, 2)
        self.identity = DriveIdentity(device_type, vendor, product, revision, serial, rated_current_mA,
                                      rated_torque_mNm, max_torque, increments, revolutions)  # fmt: skip
        self._check_scaling(self.identity)
        self._event(
            self._clock_ns(),
            LinkEventKind.DRIVE_STATE,
            f"node {self._node}: CiA 402 device 0x{device_type:08X}, vendor {_hex(vendor)}, product "
            f"{_hex(product)}, revision {_hex(revision)}, serial {_hex(serial)}; rated current "
            f"{rated_current_mA} mA, rated torque {rated_torque_mNm} mNm, max torque {max_torque} per mille",
        )
        self._write(node, 0x6060, codec.MODE_CYCLIC_SYNC_TORQUE)
        mode = self._read(node, 0x6061)
        if mode != codec.MODE_CYCLIC_SYNC_TORQUE:
            raise DriveFault(
                f"node {self._node}: modes of operation display 0x6061 = {mode} after writing 0x6060 = "
                f"{codec.MODE_CYCLIC_SYNC_TORQUE} (cyclic synchronous torque)"
            )
        self._map_pdos(node)
        if self._has(node, 0x1006):
            self._write(node, 0x1006, self._period_ns // 1000)
        if self._options.sync_counter:
            if not self._has(node, 0x1019):
                raise ConfigError("drive.cia402.sync_counter", "the EDS has no SYNC counter overflow 0x1019")
            self._write(node, 0x1019, codec.SYNC_COUNTER_MAX)
        if self._has(node, 0x1017):
            self._write(node, 0x1017, self._options.heartbeat_ms)
        self._nmt(NmtCommand.START)
        self._started = True

    def _check_scaling(self, ident: DriveIdentity) -> None:
        drive = self._drive
        if ident.rated_current_mA <= 0:
            raise ConfigError(
                "drive.cia402", f"the drive's rated current 0x6075 is {ident.rated_current_mA} mA"
            )
        if ident.rated_torque_mNm <= 0:
            raise ConfigError(
                "drive.cia402", f"the drive's rated torque 0x6076 is {ident.rated_torque_mNm} mNm"
            )
        lsb_A = Fraction(ident.rated_current_mA, 1_000_000)
        if abs(Fraction(drive.dac_lsb_A) - lsb_A) > lsb_A * Fraction(1, 10**9):
            raise ConfigError(
                "drive.dac_lsb_A",
                f"{drive.dac_lsb_A} A contradicts the drive: 1 per mille of rated current 0x6075 = "
                f"{ident.rated_current_mA} mA is {float(lsb_A):g} A",
            )
        max_A = Fraction(ident.max_torque_permille) * lsb_A
        if Fraction(drive.current_limit_A) > max_A:
            raise ConfigError(
                "drive.current_limit_A",
                f"{drive.current_limit_A} A is above the drive's max torque 0x6072 = "
                f"{ident.max_torque_permille} per mille of rated current {ident.rated_current_mA} mA "
                f"({float(max_A):g} A)",
            )
        if ident.encoder_revolutions <= 0:
            raise ConfigError("drive.encoder_counts_per_unit", "the drive's 0x608F:2 (revolutions) is 0")
        per_rev = ident.encoder_increments / ident.encoder_revolutions
        if not math.isclose(per_rev, drive.encoder_counts_per_unit, rel_tol=1e-9):
            raise ConfigError(
                "drive.encoder_counts_per_unit",
                f"{drive.encoder_counts_per_unit:g} contradicts the drive's position encoder resolution "
                f"0x608F = {ident.encoder_increments} increments / {ident.encoder_revolutions} revolution(s)",
            )

    def _map_pdos(self, node: Any) -> None:
        """RPDO1/TPDO1 (and TPDO2) as in :mod:`codec`, transmission type 1; PDOs 1..4 not used are
        disabled. canopen's ``PdoMap.save`` writes the COB-ID with bit 31 set (disabled), the
        transmission type, mapping count 0, the entries, the count, then the COB-ID valid."""
        used: dict[tuple[str, int], tuple[tuple[int, int, int], ...]] = {
            ("rpdo", 1): codec.RPDO1_MAP,
            ("tpdo", 1): codec.TPDO1_MAP,
        }
        if self._options.map_velocity:
            used[("tpdo", 2)] = codec.TPDO2_MAP
        for kind, base in (("rpdo", codec.RPDO1_BASE), ("tpdo", codec.TPDO1_BASE)):
            maps = getattr(node, kind).map
            for k, number in used:
                if k == kind and number not in maps:
                    raise ConfigError("drive.cia402.eds", f"the EDS has no {kind.upper()}{number}")
            for number, pdo_map in sorted(maps.items()):
                if number > 4:
                    break
                layout = used.get((kind, number))
                pdo_map.clear()
                pdo_map.cob_id = base + (number - 1) * 0x100 + self._node
                pdo_map.enabled = layout is not None
                for index, subindex, bits in layout or ():
                    if pdo_map.add_variable(index, subindex, bits) is None:
                        raise ConfigError("drive.cia402.eds", f"the EDS has no object 0x{index:04X} to map")
                if layout is not None:
                    pdo_map.trans_type = 1
                self._sdo(f"{kind.upper()}{number} mapping", pdo_map.save)

    def _power_up(self, node: Any, timeout_ns: int) -> None:
        """Controlword over SDO until the statusword says OPERATION_ENABLED."""
        deadline_ns = time.monotonic_ns() + timeout_ns
        resets = 0
        while True:
            statusword = self._read(node, 0x6041)
            state = self._note_statusword(statusword, "SDO")
            if state is PowerState.OPERATION_ENABLED:
                self._controlword = Command.ENABLE_OPERATION.word
                return
            if time.monotonic_ns() >= deadline_ns:
                raise self._stuck(node, statusword, state, timeout_ns)
            command = None if state is None else codec.command_towards_enabled(state)
            if command is Command.FAULT_RESET:
                if resets >= 1:  # one reset per enable; a fault that stays is reported
                    raise self._stuck(node, statusword, state, timeout_ns)
                resets += 1
                for word in codec.fault_reset_words():
                    self._write(node, 0x6040, word)
            elif command is not None:
                self._write(node, 0x6040, command.word)
            if command is None or not self._lockstep:
                time.sleep(STATE_POLL_S)

    def _stuck(self, node: Any, statusword: int, state: PowerState | None, timeout_ns: int) -> DriveFault:
        try:
            error_code = f"0x{self._read(node, 0x603F):04X}" if self._has(node, 0x603F) else "not in the EDS"
        except DobHilError:
            error_code = "unreadable"
        emcy = "" if self._last_emcy is None else f"; last EMCY {self._last_emcy.describe()}"
        return DriveFault(
            f"node {self._node}: the drive is stuck in {state.name if state else 'an undefined state'} "
            f"(statusword 0x6041 = 0x{statusword:04X}, error code 0x603F = {error_code}) after "
            f"{timeout_ns / 1e6:g} ms of trying to enable it{emcy}"
        )

    # --- SDO helpers (canopen) -------------------------------------------------------------------------
    @staticmethod
    def _has(node: Any, index: int, subindex: int = 0) -> bool:
        od = node.object_dictionary
        if index not in od:
            return False
        entry = od[index]
        return subindex == 0 or (hasattr(entry, "subindices") and subindex in entry.subindices)

    def _variable(self, node: Any, index: int, subindex: int) -> Any:
        if not self._has(node, index, subindex):
            where = f"0x{index:04X}" + (f":{subindex}" if subindex else "")
            raise ConfigError("drive.cia402.eds", f"{self._options.eds_path.name} has no object {where}")
        return node.sdo[index][subindex] if subindex else node.sdo[index]

    def _read(self, node: Any, index: int, subindex: int = 0) -> int:
        var = self._variable(node, index, subindex)
        return int(self._sdo(f"reading 0x{index:04X}:{subindex}", lambda: var.raw))

    def _write(self, node: Any, index: int, value: int, subindex: int = 0) -> None:
        var = self._variable(node, index, subindex)

        def write() -> None:
            var.raw = value

        self._sdo(f"writing 0x{index:04X}:{subindex} = {value}", write)

    def _sdo(self, what: str, transfer: Callable[[], Any]) -> Any:
        try:
            return transfer()
        except SdoAbortedError as exc:
            raise DriveFault(f"node {self._node}: SDO {what} aborted by the drive: {exc}") from None
        except SdoCommunicationError as exc:
            if self._pump_error is not None:
                raise DriveFault(f"node {self._node}: SDO {what}: {self._pump_error!r}") from self._pump_error
            raise DriveFault(
                f"node {self._node}: SDO {what}: no valid answer within "
                f"{self._options.sdo_timeout_ms} ms ({exc})"
            ) from None
        except can.CanError as exc:
            raise DriveFault(f"node {self._node}: SDO {what}: sending failed: {exc}") from None

    def _nmt(self, command: NmtCommand) -> None:
        self._send(codec.NMT_ID, codec.encode_nmt(command, self._node), f"NMT {command.name}")
        network = self._network
        if network is not None and network.after_send is not None:  # lockstep configuration
            network.after_send()

    # --- the configuration pump ----------------------------------------------------------------------
    def _on_config_tx(self, msg: can.Message) -> None:
        self.stats.tx_frames += 1
        if self._frame_hook is not None:
            with self._lock:
                self._frame_hook(msg, False)

    def _start_pump(self, network: _HookedNetwork) -> None:
        """Real time: a thread reading the drive's frames while the SDO calls wait for answers."""
        self._pump_stop.clear()
        self._pump_error = None
        self._pump = threading.Thread(target=self._pump_loop, args=(network,),
                                      name=f"cia402-config-{self._node}", daemon=True)  # fmt: skip
        self._pump.start()

    def _stop_pump(self) -> None:
        pump = self._pump
        if pump is None:
            return
        self._pump_stop.set()
        pump.join()
        self._pump = None

    def _pump_loop(self, network: _HookedNetwork) -> None:
        recv = self._bus.recv
        try:
            while not self._pump_stop.is_set():
                msg = recv(0.005)
                while msg is not None:
                    with self._lock:
                        self._take_config_frame(network, msg)
                    msg = recv(0.0)
        except BaseException as exc:  # reported by the SDO call that times out
            self._pump_error = exc

    def _settle_config(self, network: _HookedNetwork, service: Callable[[], int]) -> None:
        """Lockstep configuration, after each frame sent: service the drive and act on every frame
        it sent, until it has nothing left to do."""
        recv = self._bus.recv
        with self._lock:
            try:
                for _ in range(SETTLE_ROUNDS):
                    worked = service() > 0
                    while (msg := recv(0.0)) is not None:
                        worked = True
                        self._take_config_frame(network, msg)
                    if not worked:
                        return
            except DobHilError:
                raise
            except can.CanError as exc:  # a receive, or the drive's own send: not canopen's to retry
                raise DriveFault(f"node {self._node}: the CAN bus failed while configuring: {exc}") from exc
            except Exception as exc:  # service() raised: the embedded drive failed while configured
                raise DriveFault(f"node {self._node}: configuring the drive: {exc!r}") from exc

    def _take_config_frame(self, network: _HookedNetwork, msg: can.Message) -> None:
        """A frame received while configuring: consumed, and an SDO answer handed to canopen."""
        self._consume(msg)
        if msg.arbitration_id == self._ids["SDO_TX"] and not msg.is_error_frame:
            network.notify(msg.arbitration_id, msg.data, msg.timestamp)

    # --- the cyclic phase ---------------------------------------------------------------------------------
    def send_trigger(self) -> int:
        """Send one SYNC (the drive samples and applies on it); returns clock_ns() after sending.

        Frames still queued are read first: a TPDO1 among them answered an older SYNC (stale)."""
        if self._awaiting_tpdo:  # drain(), with its first read inline (the per-sample path)
            self.stats.missed_feedback += 1
        self._awaiting_tpdo = False
        try:
            msg = self._bus.recv(0.0)
        except can.CanError as exc:
            raise DriveFault(f"node {self._node}: receiving from the CAN bus failed: {exc}") from exc
        if msg is not None:
            self._consume(msg)
            self._drain_reads(MAX_READS_AFTER_DEADLINE - 1)
        self._awaiting_tpdo = True
        if self._options.sync_counter:
            self._sync_counter = self._sync_counter % codec.SYNC_COUNTER_MAX + 1
            self._send(codec.SYNC_ID, codec.encode_sync(self._sync_counter), "SYNC")
        else:  # the one SYNC frame there is, built once (nobody changes a frame once sent)
            self._send(codec.SYNC_ID, b"", "SYNC", self._sync_msg)
        self.stats.syncs += 1
        return self._clock_ns()

    def drain(self) -> None:
        """Read the frames already queued (non-blocking); a pending SYNC's answer is missed from now."""
        if self._awaiting_tpdo:
            self.stats.missed_feedback += 1
        self._awaiting_tpdo = False
        self._drain_reads(MAX_READS_AFTER_DEADLINE)

    def _drain_reads(self, max_reads: int) -> None:
        recv = self._bus.recv
        for _ in range(max_reads):
            msg = self._recv(recv, 0.0)
            if msg is None:
                return
            self._consume(msg)

    def receive_feedback(self, timeout_ns: int) -> Feedback | None:
        """The TPDO1 answering the last SYNC as Feedback, or None after ``timeout_ns`` (wall clock)."""
        if self._closed:
            self._check_open()
        recv = self._bus.recv
        clock_ns = self._clock_ns
        hook = self._frame_hook
        tpdo1_id = self._tpdo1_id
        if timeout_ns > 0:
            deadline_ns = time.monotonic_ns() + timeout_ns
            timeout_s = timeout_ns * 1e-9
        else:
            deadline_ns, timeout_s = 0, 0.0
        reads_after_deadline = 0
        while True:
            try:
                msg = recv(timeout_s)
            except can.CanError as exc:
                raise DriveFault(f"node {self._node}: receiving from the CAN bus failed: {exc}") from exc
            if msg is None:
                return None
            now_ns = clock_ns()
            if hook is not None:
                hook(msg, True)
            self.stats.rx_frames += 1
            if msg.arbitration_id == tpdo1_id and not (
                msg.is_error_frame or msg.is_extended_id or msg.is_remote_frame or msg.is_fd
            ):  # _dispatch's verdict for the cyclic answer, without the call
                data = msg.data
                if len(data) == _TPDO1_SIZE and self._awaiting_tpdo:
                    # _on_tpdo1's common case, inline (the per-period path): the awaited answer, the
                    # statusword unchanged in OPERATION ENABLED, a plausible encoder step; the same
                    # effects and result
                    statusword, raw_counts = _TPDO1_UNPACK(data)
                    unwrap = self._unwrapper
                    last = unwrap._last
                    state = self._state
                    if statusword == self._statusword and state is _OPERATION_ENABLED and last is not None:
                        half = unwrap._half
                        step = ((raw_counts - last + half) & unwrap._mask) - half  # update_step
                        max_step = self._max_counts_step
                        if -max_step <= step <= max_step:
                            self._awaiting_tpdo = False
                            unwrap._last = raw_counts
                            unwrap._position = counts = unwrap._position + step
                            stats = self.stats
                            stats.feedback += 1
                            return tuple.__new__(Feedback, (
                                now_ns,
                                (stats.syncs - 1) & 0xFF,
                                (raw_counts,),
                                (counts,),
                                (counts / self._counts_per_unit,),
                                True,
                                bool(statusword & _SW_FAULT),
                                bool(statusword & _INTERNAL_LIMIT),
                            ))  # fmt: skip
                feedback = self._on_tpdo1(msg, now_ns)
            else:
                feedback = self._dispatch(msg, now_ns)
            if feedback is not None:
                return feedback
            remaining_ns = deadline_ns - time.monotonic_ns() if deadline_ns else 0
            if remaining_ns > 0:
                timeout_s = remaining_ns * 1e-9
            else:
                timeout_s = 0.0
                reads_after_deadline += 1
                if reads_after_deadline > MAX_READS_AFTER_DEADLINE:
                    return None

    def quantize(self, current_A: tuple[float, ...]) -> tuple[tuple[int, ...], tuple[float, ...], bool]:
        """((per mille,), (per mille * dac_lsb_A,), saturated), clamped at the current limit; a
        non-finite current gives 0 and an INVALID_COMMAND event.

        (An instance's ``quantize`` is its quantizer's own method, bound in ``__init__``, which
        reports a non-finite current to :meth:`_nonfinite_current`: one call per period.)"""
        return self._quantizer.quantize(current_A)

    def _nonfinite_current(self, u: float) -> None:
        self.stats.nonfinite_currents += 1
        self._event(
            self._clock_ns(),
            LinkEventKind.INVALID_COMMAND,
            f"node {self._node}: non-finite current {u!r} A requested; 0 per mille commanded",
        )

    def send_command(self, codes: tuple[int, ...], answers_seq: int) -> int:
        """RPDO1: the controlword (enable operation while enabled) and the target torque in per
        mille, clamped at the limit; acts at the next SYNC. Returns clock_ns() after sending."""
        if len(codes) != N_AXES:
            raise ProtocolError(f"RPDO1: the cia402 profile drives 1 axis, got {len(codes)} codes")
        code = codes[0]
        limit = self._limit_code
        limited = -limit if code < -limit else limit if code > limit else code
        if limited != code:
            self.stats.clamped_commands += 1
        try:
            payload = _RPDO1.pack(self._controlword, limited)
        except struct.error:
            payload = codec.encode_rpdo1(self._controlword, limited)  # raises its ProtocolError
        self._send(self._rpdo1_id, payload, "RPDO1")
        return self._clock_ns()

    def describe_fault(self, wait_ns: int = 0) -> str:
        """What the drive said about its fault: statusword state and the last EMCY (frames still
        queued, or arriving within ``wait_ns``, are read first)."""
        deadline_ns = time.monotonic_ns() + wait_ns
        while True:
            remaining_ns = deadline_ns - time.monotonic_ns()
            msg = self._recv(self._bus.recv, max(remaining_ns, 0) * 1e-9)
            if msg is None:
                break
            self._consume(msg)
            if self._last_emcy is not None and not self._last_emcy.is_reset:
                break
        state = "unknown state" if self._state is None else self._state.name
        sw = "" if self._statusword is None else f" (statusword 0x{self._statusword:04X})"
        emcy = "no EMCY received" if self._last_emcy is None else f"EMCY {self._last_emcy.describe()}"
        return f"node {self._node}: {state}{sw}, {emcy}"

    # --- frame handling ---------------------------------------------------------------------------------
    def _recv(
        self, recv: Callable[[float | None], can.Message | None], timeout_s: float
    ) -> can.Message | None:
        try:
            return recv(timeout_s)
        except can.CanError as exc:
            raise DriveFault(f"node {self._node}: receiving from the CAN bus failed: {exc}") from exc

    def _consume(self, msg: can.Message) -> None:
        now_ns = self._clock_ns()
        if self._frame_hook is not None:
            self._frame_hook(msg, True)
        self.stats.rx_frames += 1
        self._dispatch(msg, now_ns)

    def _dispatch(self, msg: can.Message, now_ns: int) -> Feedback | None:
        if msg.is_error_frame:
            self.stats.error_frames += 1
            self._event(now_ns, LinkEventKind.ERROR_FRAME, f"CAN error frame {_describe(msg)}")
            return None
        if msg.is_extended_id or msg.is_remote_frame:
            self.stats.foreign_frames += 1
            what = "29-bit id" if msg.is_extended_id else "remote frame"
            self._event(now_ns, LinkEventKind.FOREIGN_FRAME, f"{what} {_describe(msg)} skipped")
            return None
        handler = self._handlers.get(msg.arbitration_id)
        if handler is None:
            if msg.arbitration_id in self._own_tx_ids:
                self.stats.own_echoes += 1
                return None
            self.stats.foreign_frames += 1
            self._event(
                now_ns, LinkEventKind.FOREIGN_FRAME, f"{_describe(msg)} is no frame of node {self._node}"
            )
            return None
        if msg.is_fd:
            self._malformed(now_ns, msg, "a CAN FD frame; CiA 301 here is classic CAN")
            return None
        return handler(msg, now_ns)

    def _on_tpdo1(self, msg: can.Message, now_ns: int) -> Feedback | None:
        data = msg.data
        if len(data) != _TPDO1_SIZE:
            self._malformed(now_ns, msg, f"TPDO1 carries {_TPDO1_SIZE} bytes as mapped, got {len(data)}")
            return None
        statusword, raw_counts = _TPDO1_UNPACK(data)
        if not self._awaiting_tpdo:
            self.stats.stale_feedback += 1
            self._event(now_ns, LinkEventKind.STALE_FEEDBACK,
                        f"node {self._node}: TPDO1 {bytes(data).hex()} answers no pending SYNC "
                        "(a duplicate or late), discarded")  # fmt: skip
            return None
        self._awaiting_tpdo = False
        if statusword == self._statusword:  # _note_statusword's shortcut, without the call
            state = self._state
        else:
            state = self._note_statusword(statusword, "TPDO1", now_ns)
        counts, step_or_none = self._unwrapper.update_step(raw_counts)
        step = 0 if step_or_none is None else step_or_none
        if step > self._max_counts_step or step < -self._max_counts_step:
            self.stats.encoder_jumps += 1
            self._event(now_ns, LinkEventKind.ENCODER_JUMP,
                        f"node {self._node}: position step {step} increments exceeds the plausibility "
                        f"bound {self._max_counts_step}")  # fmt: skip
        stats = self.stats
        stats.feedback += 1
        # Feedback(...) without the NamedTuple's Python-level __new__ (the per-sample path)
        return tuple.__new__(Feedback, (
            now_ns,
            (stats.syncs - 1) & 0xFF,
            (raw_counts,),
            (counts,),
            (counts / self._counts_per_unit,),
            state is _OPERATION_ENABLED,
            bool(statusword & _SW_FAULT) or state is _FAULT or state is _FAULT_REACTION,
            bool(statusword & _INTERNAL_LIMIT),
        ))  # fmt: skip

    def _on_tpdo2(self, msg: can.Message, now_ns: int) -> None:
        try:
            self._velocity = codec.decode_tpdo2(msg.data)
        except ProtocolError as exc:
            self._malformed(now_ns, msg, str(exc))

    def _on_emcy(self, msg: can.Message, now_ns: int) -> None:
        try:
            emcy = codec.decode_emcy(msg.data)
        except ProtocolError as exc:
            self._malformed(now_ns, msg, str(exc))
            return
        self._last_emcy = emcy
        self.stats.emcy += 1
        if emcy.is_reset:
            self._event(now_ns, LinkEventKind.DRIVE_STATE, f"node {self._node}: EMCY {emcy.describe()}")
        else:
            self._event(now_ns, LinkEventKind.DRIVE_FAULT, f"node {self._node}: EMCY {emcy.describe()}")

    def _on_heartbeat(self, msg: can.Message, now_ns: int) -> None:
        try:
            state = codec.decode_heartbeat(msg.data)
        except ProtocolError as exc:
            self._malformed(now_ns, msg, str(exc))
            return
        if state is not self._nmt_state:
            old = "unknown" if self._nmt_state is None else self._nmt_state.name
            self._nmt_state = state
            self._event(
                now_ns, LinkEventKind.DRIVE_STATE, f"node {self._node}: NMT {old} -> {state.name} (heartbeat)"
            )

    def _on_sdo_answer(self, msg: can.Message, now_ns: int) -> None:
        """SDO answers reach canopen while configuring; one arriving in the cyclic phase is late."""
        if not self._configuring:
            self.stats.foreign_frames += 1
            self._event(
                now_ns, LinkEventKind.FOREIGN_FRAME, f"{_describe(msg)}: an SDO answer outside configuration"
            )

    def _note_statusword(self, statusword: int, source: str, now_ns: int | None = None) -> PowerState | None:
        if statusword == self._statusword:
            return self._state
        state = codec.decode_state(statusword)
        self._statusword = statusword
        if state is not self._state:
            old = "unknown" if self._state is None else self._state.name
            self._state = state
            new = "undefined" if state is None else state.name
            text = f"node {self._node}: {old} -> {new} (statusword 0x{statusword:04X}, {source})"
            self._event(self._clock_ns() if now_ns is None else now_ns, LinkEventKind.DRIVE_STATE, text)
        return state

    def _malformed(self, now_ns: int, msg: can.Message, problem: str) -> None:
        self.stats.malformed_frames += 1
        self._event(now_ns, LinkEventKind.MALFORMED_FRAME, f"{_describe(msg)} skipped: {problem}")

    def _event(self, time_ns: int, kind: LinkEventKind, message: str) -> None:
        if self._event_hook is not None:
            with self._lock:
                self._event_hook(LinkEvent(time_ns, kind, message))

    # --- sending, stopping ---------------------------------------------------------------------------------
    def _send(self, arbitration_id: int, payload: bytes, what: str, msg: can.Message | None = None) -> None:
        """Send a classic frame (``msg``: the frame of ``arbitration_id`` and ``payload``, built before)."""
        if self._closed:
            self._check_open()
        if msg is None:
            msg = data_frame(0.0, arbitration_id, payload)
        try:
            self._bus.send(msg)
        except can.CanError as exc:
            self.stats.send_failures += 1
            text = f"node {self._node}: sending {what} (id 0x{arbitration_id:03X}) failed: {exc}"
            self._event(self._clock_ns(), LinkEventKind.SEND_FAILED, text)
            raise DriveFault(text) from exc
        self.stats.tx_frames += 1
        hook = self._frame_hook
        if hook is not None:
            hook(msg, False)

    def safe_stop(self) -> None:
        """Zero torque (still enabled), disable operation, shutdown, each applied by a SYNC; then
        NMT pre-operational. Never raises; repeatable; nothing after :meth:`close`."""
        if self._closed:
            return
        self._stop_pump()
        if not self._started:
            return
        gap_s = 0.0 if self._lockstep else self._period_ns * 1e-9
        steps = (
            (self._controlword, "RPDO1 zero torque"),
            (Command.DISABLE_OPERATION.word, "RPDO1 disable operation"),
            (Command.SHUTDOWN.word, "RPDO1 shutdown"),
        )
        for word, what in steps:
            self._stop_step(
                what, functools.partial(self._send, self._rpdo1_id, codec.encode_rpdo1(word, 0), what)
            )
            self._stop_step("SYNC", lambda: self._send(codec.SYNC_ID, self._stop_sync_payload(), "SYNC"))
            if gap_s:
                time.sleep(gap_s)
        self._controlword = Command.SHUTDOWN.word
        self._stop_step("NMT enter pre-operational", lambda: self._nmt(NmtCommand.ENTER_PRE_OPERATIONAL))
        self._started = False

    def _stop_sync_payload(self) -> bytes:
        if not self._options.sync_counter:
            return b""
        self._sync_counter = self._sync_counter % codec.SYNC_COUNTER_MAX + 1
        return codec.encode_sync(self._sync_counter)


def _hex(value: int | None) -> str:
    return "?" if value is None else f"0x{value:08X}"


def _object_dictionary(path: Path, node_id: int) -> canopen.ObjectDictionary:
    """The EDS/DCF parsed for ``node_id`` (``$NODEID`` resolved): parsed once per file version and
    node, since parsing takes several ms and a campaign or benchmark enables many sessions in one
    process. The link only reads the dictionary (its SDO variables and PDO maps are the node's).
    A version is the file's device, inode, size, modification and change times: a copy that keeps
    the modification time (``cp -p``) still gets a new change time, or a new inode."""
    st = path.stat()
    version = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
    return _parse_od(str(path), version, node_id)


@functools.lru_cache(maxsize=16)
def _parse_od(path: str, version: tuple[int, ...], node_id: int) -> canopen.ObjectDictionary:
    del version  # part of the cache key: another version of the file is parsed again
    return canopen.import_od(path, node_id)


def _describe(msg: can.Message) -> str:
    if msg.is_error_frame:
        return f"(error class 0x{msg.arbitration_id:X}, data {bytes(msg.data).hex() or '-'})"
    width = 8 if msg.is_extended_id else 3
    return f"id 0x{msg.arbitration_id:0{width}X} DLC {msg.dlc} data {bytes(msg.data).hex() or '-'}"


__all__ = ["Cia402DriveLink", "Cia402Stats", "DriveIdentity"]
