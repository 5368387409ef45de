"""The current DAC: a command in DAC counts, clamped at the configured limit, applied as ``code * LSB``."""

from __future__ import annotations

import math

from dob_hil.link.protocol import saturate_current_counts


class Dac:
    def __init__(self, lsb_A: float, limit_A: float) -> None:
        if not lsb_A > 0 or not limit_A >= lsb_A:
            raise ValueError(f"DAC needs 0 < lsb_A <= limit_A, got lsb {lsb_A} A, limit {limit_A} A")
        self.lsb_A = lsb_A
        self.limit_A = limit_A
        # floor(limit / LSB); the relative nudge keeps 0.5 A / (1/2048) A from landing on 1023.999...
        self.limit_counts = math.floor(limit_A / lsb_A * (1.0 + 1e-12))

    def convert(self, current_counts: int) -> tuple[int, float, bool]:
        """(code, applied current in A, saturated) for a commanded DAC code."""
        code = saturate_current_counts(current_counts, self.limit_counts)
        return code, code * self.lsb_A, code != current_counts
