"""The ODrive CANSimple profile (firmware 0.6.x): torque control, host-clocked by RTR.

Clocking: ODrive has no SYNC. The host is the clock (``dob_hil.loop.host_clocked``): at each
absolute deadline it sends a remote request (RTR) for Get_Encoder_Estimates (``send_trigger()``),
the drive answers with the estimates sampled when the request arrives, the host runs the step and
sends Set_Input_Torque, which the drive applies when it arrives. The drive's cyclic estimates are
off (``encoder_msg_rate_ms = 0``). The link and the simulated drive also serve the drive-clocked
variant (cyclic estimates every period, sequence numbers from arrival times), used by their own
tests. ODrive's message rates are whole milliseconds, and the request, the answer and the command
must fit in a period: the profile serves 1 ms and up.

Input delay: the torque acts from its arrival, a fraction of a period after the estimates were
sampled (bus time of the RTR, the 8-byte answer and the 8-byte command, about 0.33 ms at 1 Mbit/s
worst case, plus the host's turnaround), exactly as with the native profile: no whole sample of
delay, so ``input_delay_samples = 0``; the fraction is unmodelled, as for the native profile.
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
    summary="ODrive CANSimple (firmware 0.6.x): RTR-triggered encoder estimates, Set_Input_Torque answers",
    clocking=Clocking.HOST,
    min_period_ns=1_000_000,
    max_period_ns=1_000_000_000,
    input_delay_samples=0,
    units="turns, turns/s (float32) / N m (float32)",
    make_link=_make_link,
    make_sim=_make_sim,
    bus_load=_bus_load,
    parse_options=parse_options,
    make_quantizer=_make_quantizer,
    tested="byte-exact codec, cantools DBC, watchdog, axis errors, NaN/inf, RTR-triggered lockstep and "
    "udp_multicast real time, fault matrix, drive-clocked variant",
)
