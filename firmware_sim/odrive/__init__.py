"""The simulated ODrive (CANSimple, firmware 0.6.x frames): :class:`SimulatedOdrive`."""

from __future__ import annotations

from firmware_sim.odrive.core import OdriveCore, OdriveStats
from firmware_sim.odrive.drive import SimulatedOdrive

__all__ = ["OdriveCore", "OdriveStats", "SimulatedOdrive"]
