"""``[drive.cia402]``: the settings of the CiA 402 profile (parsed by its descriptor).

::

    [drive.cia402]
    eds = "path/to/drive.eds"   # the drive's EDS or DCF; default: the generic one shipped here
    sync_counter = false        # SYNC with the 1-byte counter 1..240 (the drive's 0x1019 > 0)
    map_velocity = false        # also map velocity actual value 0x606C into TPDO2 (logged only)
    heartbeat_ms = 100          # heartbeat producer time written to the drive's 0x1017 (0: off)
    sdo_timeout_ms = 500        # how long one SDO transfer may take before it is an error

A relative ``eds`` path is taken from the working directory.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from dob_hil.config import ConfigSection
from dob_hil.errors import ConfigError

DEFAULT_EDS = Path(__file__).resolve().parent / "generic_cia402.eds"


@dataclass(frozen=True)
class Cia402Options:
    eds_path: Path = DEFAULT_EDS
    sync_counter: bool = False
    map_velocity: bool = False
    heartbeat_ms: int = 100
    sdo_timeout_ms: int = 500

    @property
    def sdo_timeout_s(self) -> float:
        return self.sdo_timeout_ms * 1e-3


def parse_options(s: ConfigSection) -> Cia402Options:
    eds = s.string("eds", "")
    eds_path = Path(eds).resolve() if eds else DEFAULT_EDS
    if not eds_path.is_file():
        raise ConfigError(s.name("eds"), f"no such EDS/DCF file: {eds_path}")
    return Cia402Options(
        eds_path=eds_path,
        sync_counter=s.boolean("sync_counter", False),
        map_velocity=s.boolean("map_velocity", False),
        heartbeat_ms=s.integer("heartbeat_ms", 100, low=0, high=65535),
        sdo_timeout_ms=s.integer("sdo_timeout_ms", 500, low=1, high=60_000),
    )


def options_of(options: object) -> Cia402Options:
    """``config.drive.options`` of a cia402 config (the defaults where the table was absent)."""
    return options if isinstance(options, Cia402Options) else Cia402Options()
