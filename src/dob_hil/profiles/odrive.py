"""The ODrive CANSimple profile (firmware 0.6.x): torque control, drive-clocked encoder estimates.

Clocking: ODrive has no SYNC. The drive sends Get_Encoder_Estimates every
``encoder_msg_rate_ms`` (set to the control period) and the host answers each with
Set_Input_Torque, which the drive applies when it arrives. ODrive's cyclic messages are configured
in whole milliseconds, so the period is 1 ms at least and a whole number of milliseconds.

Host-clocked, the preferred clocking (no drift between two clocks, the host's deadlines are the
sample instants), is implemented in the link and the simulated drive and tested in lockstep:
``encoder_msg_rate_ms = 0`` turns the cyclic estimates off and the host's RTR
Get_Encoder_Estimates (``send_trigger()``) becomes each sample's trigger, answered with the
estimates sampled on its arrival. The profile switches to it with ``clocking=Clocking.HOST``
(and ``encoder_msg_rate_ms = 0`` in the scenario) once the host-clocked runner is in main.

Input delay: either way the torque acts from its arrival, a fraction of a period after the
estimates were sampled (bus time of the frames, about 0.27 ms at 1 Mbit/s worst case for the two
8-byte frames, plus the host's turnaround), exactly as with the native profile: no whole sample
of delay, so ``input_delay_samples = 0``; the fraction is unmodelled, as for the native profile.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dob_hil.errors import ConfigError
from dob_hil.link.odrive.options import OdriveOptions, parse_options
from dob_hil.profiles.base import Clocking, DriveProfile, QuantizeFn, SimulatedCounterpart, TruthSink

if TYPE_CHECKING:
    import can

    from dob_hil.config import Config, DriveConfig
    from dob_hil.link.base import DriveLink, EventHook, FrameHook
    from dob_hil.link.busload import BusLoad

RTR_BYTES = 0


def _make_link(bus: can.BusABC, config: Config, frame_hook: FrameHook, event_hook: EventHook) -> DriveLink:
    from dob_hil.link.odrive.link import OdriveDriveLink
    from dob_hil.link.odrive.options import odrive_options

    options = odrive_options(config, host_clocked=PROFILE.clocking is Clocking.HOST)
    return OdriveDriveLink(bus, config.drive, options, config.plant.period_ns,
                           frame_hook=frame_hook, event_hook=event_hook, owns_bus=True)  # fmt: skip


def _make_sim(
    bus: can.BusABC, config: Config, clock: str, truth_sink: TruthSink | None
) -> SimulatedCounterpart:
    from firmware_sim.odrive import SimulatedOdrive

    return SimulatedOdrive(bus, config, clock="realtime" if clock == "realtime" else "lockstep",
                           truth_sink=truth_sink)  # fmt: skip


def _make_quantizer(drive: DriveConfig) -> QuantizeFn:
    from dob_hil.link.odrive.link import TorqueQuantizer

    if not isinstance(drive.options, OdriveOptions):
        raise ConfigError("drive.odrive", "missing (the ODrive profile needs this table)")
    return TorqueQuantizer(drive.current_limit_A, drive.options.torque_constant_Nm_per_A).quantize


def _bus_load(config: Config) -> BusLoad:
    from dob_hil.link.busload import cyclic_bus_load
    from dob_hil.link.odrive.codec import DLC
    from dob_hil.link.odrive.options import odrive_options

    options = odrive_options(config, host_clocked=PROFILE.clocking is Clocking.HOST)
    period_ns = config.plant.period_ns
    heartbeat_hz = 1000.0 / options.heartbeat_msg_rate_ms
    frames = {
        **({"Get_Encoder_Estimates RTR": (RTR_BYTES, 1.0)} if options.encoder_msg_rate_ms == 0 else {}),
        "Get_Encoder_Estimates": (DLC, 1.0),
        "Set_Input_Torque": (DLC, 1.0),
        "Heartbeat": (DLC, heartbeat_hz * period_ns * 1e-9),
    }
    return cyclic_bus_load(config.drive.bitrate_bps, period_ns, frames, heartbeat_hz=heartbeat_hz)


PROFILE = DriveProfile(
    name="odrive",
    summary="ODrive CANSimple (firmware 0.6.x): cyclic encoder estimates, Set_Input_Torque answers",
    clocking=Clocking.DRIVE,
    min_period_ns=1_000_000,
    max_period_ns=1_000_000_000,
    input_delay_samples=0,
    units="turns, turns/s (float32) / N m (float32)",
    make_link=_make_link,
    make_sim=_make_sim,
    bus_load=_bus_load,
    parse_options=parse_options,
    make_quantizer=_make_quantizer,
    tested="byte-exact codec, cantools DBC, watchdog, axis errors, NaN/inf, lockstep and udp_multicast "
    "real time, fault matrix",
)
