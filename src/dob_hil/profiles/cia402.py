"""The CANopen CiA 402 profile: cyclic synchronous torque, the host sends SYNC (host-clocked).

The drive samples its position at each SYNC (TPDO1, transmission type 1) and applies the target
torque received before a SYNC at that SYNC: a setpoint computed from sample k acts from sample
k + 1, one period of input delay that the design must model (``plant.input_delay_samples = 1``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dob_hil.profiles.base import Clocking, DriveProfile, SimulatedCounterpart, TruthSink

if TYPE_CHECKING:
    import can

    from dob_hil.config import Config, ConfigSection
    from dob_hil.link.base import DriveLink, EventHook, FrameHook
    from dob_hil.link.busload import BusLoad

HEARTBEAT_BYTES = 1
SYNC_BYTES = {False: 0, True: 1}
RPDO1_BYTES = 4  # controlword + target torque
TPDO1_BYTES = 6  # statusword + position actual value
TPDO2_BYTES = 4  # velocity actual value


def _make_link(bus: can.BusABC, config: Config, frame_hook: FrameHook, event_hook: EventHook) -> DriveLink:
    from dob_hil.link.cia402.link import Cia402DriveLink

    return Cia402DriveLink(bus, config, frame_hook=frame_hook, event_hook=event_hook, owns_bus=True)


def _make_sim(
    bus: can.BusABC, config: Config, clock: str, truth_sink: TruthSink | None
) -> SimulatedCounterpart:
    from firmware_sim.cia402 import SimulatedCia402Drive

    drive: SimulatedCounterpart = SimulatedCia402Drive(
        bus, config, clock="realtime" if clock == "realtime" else "lockstep", truth_sink=truth_sink
    )
    return drive


def _bus_load(config: Config) -> BusLoad:
    from dob_hil.link.busload import cyclic_bus_load
    from dob_hil.link.cia402.options import options_of

    options = options_of(config.drive.options)
    period_ns = config.plant.period_ns
    heartbeat_hz = 1000.0 / options.heartbeat_ms if options.heartbeat_ms else 0.0
    frames = {
        "SYNC": (SYNC_BYTES[options.sync_counter], 1.0),
        "RPDO1": (RPDO1_BYTES, 1.0),
        "TPDO1": (TPDO1_BYTES, 1.0),
        "HEARTBEAT": (HEARTBEAT_BYTES, heartbeat_hz * period_ns * 1e-9),
    }
    if options.map_velocity:
        frames["TPDO2"] = (TPDO2_BYTES, 1.0)
    return cyclic_bus_load(config.drive.bitrate_bps, period_ns, frames, heartbeat_hz=heartbeat_hz)


def _parse_options(section: ConfigSection) -> object:
    from dob_hil.link.cia402.options import parse_options

    return parse_options(section)


PROFILE = DriveProfile(
    name="cia402",
    summary="CANopen CiA 402 cyclic synchronous torque: the host sends SYNC, TPDO/RPDO every period",
    clocking=Clocking.HOST,
    min_period_ns=100_000,
    max_period_ns=1_000_000_000,
    input_delay_samples=1,
    units="position actual value 0x6064 (increments) / target torque 0x6071 (per mille of rated)",
    make_link=_make_link,
    make_sim=_make_sim,
    bus_load=_bus_load,
    parse_options=_parse_options,
    tested="codec byte for byte, frames decoded by canopen's PDO maps, state machine, lockstep "
    "and udp_multicast real time against firmware_sim.cia402, fault matrix",
)
