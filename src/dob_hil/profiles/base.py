"""What a drive profile is: the pieces the session needs to run one kind of drive.

A profile is a self-contained set of modules: a pure codec, a host link implementing
:class:`~dob_hil.link.base.DriveLink`, and a simulated counterpart in ``firmware_sim`` that speaks
the same wire format. This module holds the descriptor that ties them together; the registry
(:mod:`dob_hil.profiles`) finds every descriptor on its own, so adding a profile touches no other
module.

Two clockings exist:

- ``Clocking.DRIVE``: the drive samples on its own clock and sends feedback every period; the host
  answers each feedback at once (native protocol, ODrive's cyclic encoder estimates).
- ``Clocking.HOST``: the host is the clock; it sends a SYNC at each absolute deadline and the drive
  samples and applies setpoints on it (CANopen CiA 402 cyclic synchronous modes).
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    import can

    from dob_hil.config import Config, ConfigSection, DriveConfig
    from dob_hil.link.base import DriveLink, EventHook, FrameHook
    from dob_hil.link.busload import BusLoad


class Clocking(enum.Enum):
    DRIVE = "drive"  # the drive's feedback is the clock; the host answers each sample
    HOST = "host"  # the host sends SYNC at absolute deadlines; the drive follows


class SimulatedCounterpart(Protocol):
    """A profile's simulated drive as the session drives it (see ``firmware_sim``)."""

    def service(self) -> int:
        """Lockstep: act on every pending frame; returns how many were read."""

    def advance_period(self) -> None:
        """Lockstep: one period passes without a command reaching the drive."""

    @property
    def period_index(self) -> int: ...

    @property
    def time_ns(self) -> int:
        """Simulated time the physics has been integrated to."""

    @property
    def enabled(self) -> bool:
        """The drive applies current (its power stage is on)."""

    def start(self) -> None:
        """Real time: start the drive's own threads. Nothing in lockstep."""

    def stop(self) -> None:
        """Real time: stop the threads (safe to call twice). Nothing in lockstep."""


TruthSink = Callable[[Any], None]
QuantizeFn = Callable[[tuple[float, ...]], tuple[tuple[int, ...], tuple[float, ...], bool]]


@dataclass(frozen=True)
class DriveProfile:
    """One drive profile: its limits, how to build its link and its simulated counterpart."""

    name: str
    summary: str  # one line for the catalogue
    clocking: Clocking
    min_period_ns: int  # the shortest control period the profile can serve
    max_period_ns: int
    input_delay_samples: int  # samples of input delay the profile's timing adds (to model in the design)
    units: str  # what travels on the wire, for the catalogue (e.g. "counts / DAC codes")
    make_link: Callable[[can.BusABC, Config, FrameHook, EventHook], DriveLink]
    make_sim: Callable[[can.BusABC, Config, str, TruthSink | None], SimulatedCounterpart]
    bus_load: Callable[[Config], BusLoad]  # worst-case cyclic load for a config
    parse_options: Callable[[ConfigSection], object] | None = None  # the [drive.<name>] table
    tested: str = ""  # what the test suite covers, for the catalogue
    # the link's quantize() as a pure function of the drive config, for `replay` (None: DacQuantizer)
    make_quantizer: Callable[[DriveConfig], QuantizeFn] | None = None
    max_axes: int = 1  # drive nodes one link drives on one bus (an axis: one plant input and output)

    def check_axes(self, config: Config) -> None:
        """Refuse, before any bus opens, a plant the profile cannot drive: not square (axis i is
        input i and output i), more axes than :attr:`max_axes`, or without one node per axis."""
        from dob_hil.errors import ConfigError
        from dob_hil.link.axes import axis_node_ids, check_square

        n_axes = check_square(config.plant)
        if n_axes > self.max_axes:
            raise ConfigError(
                "plant.B",
                f"the {self.name} profile drives {self.max_axes} axis (one current input); the "
                f"plant has {n_axes} inputs",
            )
        if n_axes > 1:
            axis_node_ids(config.drive, n_axes)

    def check_period(self, period_ns: int) -> None:
        """Refuse a control period the profile cannot serve, naming both numbers."""
        from dob_hil.errors import ConfigError

        if not self.min_period_ns <= period_ns <= self.max_period_ns:
            raise ConfigError(
                "plant.period_us",
                f"{period_ns / 1000:g} us is outside what the {self.name} profile serves "
                f"({self.min_period_ns / 1000:g} to {self.max_period_ns / 1000:g} us)",
            )
