"""The native protocol profile: dob_hil's own 6-byte feedback / 3-byte command (drive-clocked)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from dob_hil.profiles.base import Clocking, DriveProfile, QuantizeFn, SimulatedCounterpart, TruthSink

if TYPE_CHECKING:
    import can

    from dob_hil.config import Config, DriveConfig
    from dob_hil.link.base import DriveLink, EventHook, FrameHook
    from dob_hil.link.busload import BusLoad


def _make_link(bus: can.BusABC, config: Config, frame_hook: FrameHook, event_hook: EventHook) -> DriveLink:
    """One node for a single-input plant; one node per axis (``drive.node_ids``) for N inputs."""
    from dob_hil.link.axes import check_square

    n_axes = check_square(config.plant)
    if n_axes > 1:
        from dob_hil.link.native_axes import MultiAxisNativeLink

        return MultiAxisNativeLink(bus, config.drive, n_axes, frame_hook=frame_hook, event_hook=event_hook,
                                   owns_bus=True, period_ns=config.plant.period_ns)  # fmt: skip
    from dob_hil.link.native import NativeDriveLink

    return NativeDriveLink(bus, config.drive, frame_hook=frame_hook, event_hook=event_hook, owns_bus=True)


def _make_sim(
    bus: can.BusABC, config: Config, clock: str, truth_sink: TruthSink | None
) -> SimulatedCounterpart:
    from firmware_sim.axes import make_simulated_drive

    return make_simulated_drive(bus, config, clock="realtime" if clock == "realtime" else "lockstep",
                                truth_sink=truth_sink)  # fmt: skip


def _make_quantizer(drive: DriveConfig) -> QuantizeFn:
    """Each axis's DAC on its own current (one axis: DacQuantizer), for `replay`."""
    from dob_hil.link.native_axes import axes_quantizer

    return axes_quantizer(drive)


def _bus_load(config: Config) -> BusLoad:
    from dob_hil.link.busload import worst_case_bus_load

    return worst_case_bus_load(config.drive, config.plant.period_ns, n_axes=config.plant.n_inputs)


PROFILE = DriveProfile(
    max_axes=16,  # node ids 0..15
    name="native",
    summary="dob_hil's own protocol: FEEDBACK every period from the drive, COMMAND answers it",
    clocking=Clocking.DRIVE,
    min_period_ns=50_000,
    max_period_ns=1_000_000_000,
    input_delay_samples=0,
    units="encoder counts (i32) / DAC codes (i16)",
    make_link=_make_link,
    make_sim=_make_sim,
    bus_load=_bus_load,
    make_quantizer=_make_quantizer,
    tested="byte-exact codec, cantools DBC, lockstep and udp_multicast real time, fault matrix, "
    "several axes (2x2 on two nodes, lockstep and real time)",
)
