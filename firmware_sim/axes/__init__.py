"""Several axes (drive nodes) on one bus sharing one coupled plant: the multi-axis simulated drive."""

from __future__ import annotations

from firmware_sim.axes.core import AxesTruth, MultiAxisCore
from firmware_sim.axes.drive import MultiAxisDrive, make_simulated_drive

__all__ = ["AxesTruth", "MultiAxisCore", "MultiAxisDrive", "make_simulated_drive"]
