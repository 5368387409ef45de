"""dob_hil: a hardware-in-the-loop bridge for a discrete-time state-space disturbance observer."""

from __future__ import annotations

__version__ = "0.1.0"
__all__ = ["__version__"]
