"""Faults the simulated drive injects on its own, from the config's ``[sim.faults]``.

They act inside the drive, so they work the same with the embedded drive (lockstep or real
time) and with ``python -m firmware_sim`` in its own process. Each is tied to the period
``N = max(1, round(t_s / Ts))`` periods after the drive was first enabled (the start of a run; a
standalone drive's clock starts earlier, with its process), counted on the drive's own clock:

* ``fault_at_s``: at the period boundary of sample N the drive enters FAULT (code OVERCURRENT,
  as a power stage would): zero current, a FAULT frame and a HEARTBEAT, and feedback N on carries
  the FAULT status. Once: after CLEAR_FAULT the drive does not fault again.
* ``silent_at_s``: from sample N on the drive sends no frame at all (feedback, heartbeats,
  faults); it still acts on every frame it receives (a dead transmitter, not a dead drive).
* ``encoder_jump_at_s`` / ``encoder_jump_counts``: from sample N on the encoder counter reads
  ``encoder_jump_counts`` more than the true position gives (a miscount that stays), wrapped to
  the encoder's width.

:meth:`DriveFaults.from_config` returns None when nothing is configured; the drive's hooks then
cost one ``is not None`` test per period.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dob_hil.config import Config, FaultsConfig
from dob_hil.link.protocol import FaultCode
from firmware_sim.encoder import wrap_counts

if TYPE_CHECKING:
    from firmware_sim.core import DriveCore

INJECTED_FAULT_CODE = FaultCode.OVERCURRENT


def period_of(t_s: float | None, period_ns: int) -> int | None:
    """The period index of a fault time: ``max(1, round(t_s / Ts))``; None for None."""
    if t_s is None:
        return None
    return max(1, round(t_s * 1e9 / period_ns))


class DriveFaults:
    """The configured faults of one drive, by period index (see the module docstring)."""

    def __init__(self, faults: FaultsConfig, period_ns: int, encoder_bits: int) -> None:
        self.fault_period = period_of(faults.fault_at_s, period_ns)
        self.silent_period = period_of(faults.silent_at_s, period_ns)
        self.jump_period = (
            period_of(faults.encoder_jump_at_s, period_ns) if faults.encoder_jump_counts else None
        )
        self.jump_counts = faults.encoder_jump_counts
        self.encoder_bits = encoder_bits
        self.fault_injected = False
        self.silent = False  # the drive's clocks send nothing while this is set
        self.origin: int | None = None  # the drive's period index at its first enable

    @classmethod
    def from_config(cls, config: Config) -> DriveFaults | None:
        faults = config.sim.faults
        if not faults.active:
            return None
        return cls(faults, config.plant.period_ns, config.drive.encoder_bits)

    def on_enabled(self, period_index: int) -> None:
        """The drive entered ENABLED at ``period_index``; the first time sets the origin."""
        if self.origin is None:
            self.origin = period_index

    def on_period(self, core: DriveCore, period_index: int) -> None:
        """At the boundary of sample ``period_index``, before its feedback: fault, go silent."""
        if self.origin is None:
            return
        period_index -= self.origin
        if self.fault_period is not None and not self.fault_injected and period_index >= self.fault_period:
            self.fault_injected = True
            core.fault(INJECTED_FAULT_CODE, 0, core.time_ns)  # nothing if already in FAULT
        if self.silent_period is not None and period_index >= self.silent_period:
            self.silent = True
            core.silent = True

    def counts(self, period_index: int, counts: int) -> int:
        """The counter value the encoder reports for sample ``period_index`` (true: ``counts``)."""
        if (
            self.jump_period is not None
            and self.origin is not None
            and period_index - self.origin >= self.jump_period
        ):
            return wrap_counts(counts + self.jump_counts, self.encoder_bits)
        return counts
