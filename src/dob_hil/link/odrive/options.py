"""``[drive.odrive]``: what the ODrive profile needs beyond the common ``[drive]`` table.

================================ ===========================================================
key                              meaning
================================ ===========================================================
torque_constant_Nm_per_A         the drive's ``motor.config.torque_constant`` (required,
                                 finite, > 0): amperes of the controller to N m on the wire
encoder_cpr                      the encoder's counts per turn (required, >= 1): estimates in
                                 turns are quantized to it for the controller
encoder_msg_rate_ms              the drive's ``can.encoder_msg_rate_ms``. 0 (default, the
                                 shipped host-clocked profile): no cyclic estimates, the
                                 host's RTR Get_Encoder_Estimates triggers each sample. A
                                 drive-clocked loop would set it to the control period
heartbeat_msg_rate_ms            the drive's ``can.heartbeat_msg_rate_ms`` (default 10):
                                 axis errors reach the host at this rate
firmware                         the firmware line the frames follow; only "0.6"
================================ ===========================================================

``drive.clear_fault`` (``dob-hil run --clear-fault``) sends Clear_Errors before enabling.
``drive.watchdog_periods`` times the control period is the drive's watchdog timeout
(``axis.config.watchdog_timeout``), and ``drive.current_limit_A`` its current limit.
``drive.encoder_counts_per_unit`` is in encoder counts (``encoder_cpr`` per turn) per plant
output unit: with ``encoder_counts_per_unit = encoder_cpr`` the plant's unit is the turn.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from dob_hil.errors import ConfigError

if TYPE_CHECKING:
    from dob_hil.config import Config, ConfigSection

FIRMWARE_LINES = ("0.6",)
MIN_MSG_RATE_MS = 1  # ODrive's cyclic messages are configured in whole milliseconds


@dataclass(frozen=True)
class OdriveOptions:
    torque_constant_Nm_per_A: float
    encoder_cpr: int
    encoder_msg_rate_ms: int = 0
    heartbeat_msg_rate_ms: int = 10
    firmware: str = "0.6"


def parse_options(s: ConfigSection) -> OdriveOptions:
    kt = s.number("torque_constant_Nm_per_A", positive=True)  # finite and > 0, or it names the key
    if not math.isfinite(kt):  # pragma: no cover (the section reader refuses non-finite numbers)
        raise ConfigError(s.name("torque_constant_Nm_per_A"), f"must be finite, got {kt}")
    return OdriveOptions(
        torque_constant_Nm_per_A=kt,
        encoder_cpr=s.integer("encoder_cpr", low=1, high=1 << 24),
        encoder_msg_rate_ms=s.integer("encoder_msg_rate_ms", 0, low=0, high=60_000),
        heartbeat_msg_rate_ms=s.integer("heartbeat_msg_rate_ms", 10, low=MIN_MSG_RATE_MS, high=60_000),
        firmware=s.string("firmware", "0.6", FIRMWARE_LINES),
    )


def odrive_options(config: Config, *, host_clocked: bool | None = None) -> OdriveOptions:
    """The parsed ``[drive.odrive]`` table, checked against the control period and the clocking.

    Drive-clocked (``host_clocked=False``): the drive's cyclic encoder estimates clock the loop, so
    their rate must be the control period. Host-clocked (True): the host's RTR triggers each
    sample, so the cyclic estimates must be off (``encoder_msg_rate_ms = 0``). None accepts both
    (the simulated drive, which serves either). A ConfigError names the numbers otherwise.
    """
    options = config.drive.options
    if not isinstance(options, OdriveOptions):
        raise ConfigError("drive.odrive", "missing (the ODrive profile needs this table)")
    period_ns = config.plant.period_ns
    rate = options.encoder_msg_rate_ms
    if rate == 0:
        if host_clocked is False:
            raise ConfigError(
                "drive.odrive.encoder_msg_rate_ms",
                "0 (RTR-triggered estimates) needs a host-clocked profile; set it to the control "
                f"period ({period_ns / 1e6:g} ms)",
            )
    elif host_clocked is True:
        raise ConfigError(
            "drive.odrive.encoder_msg_rate_ms",
            f"{rate} ms: the host's RTR triggers each sample; set 0 (no cyclic estimates)",
        )
    elif rate * 1_000_000 != period_ns:
        raise ConfigError(
            "drive.odrive.encoder_msg_rate_ms",
            f"{rate} ms must equal the control period "
            f"({period_ns / 1e6:g} ms): the drive's encoder estimates clock the loop",
        )
    return options
