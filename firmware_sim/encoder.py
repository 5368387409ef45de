"""Incremental encoder: position to a wrapping counter, as the drive latches it at a sample instant.

``counts = floor(position * counts_per_unit + 0.5)`` (round half up), plus optional seeded
Gaussian noise in counts (rounded the same way), wrapped to ``bits`` as two's complement and
sign-extended into the int32 feedback field.
"""

from __future__ import annotations

import math
import random


def wrap_counts(counts: int, bits: int) -> int:
    """``counts`` modulo ``2**bits`` as a signed (two's complement) value."""
    span = 1 << bits
    v = counts & (span - 1)
    return v - span if v >= span >> 1 else v


class Encoder:
    def __init__(
        self, counts_per_unit: float, bits: int, noise_counts_std: float = 0.0, seed: int = 0
    ) -> None:
        if not 1 <= bits <= 32:
            raise ValueError(f"encoder bits must be 1..32, got {bits}")
        self.counts_per_unit = counts_per_unit
        self.bits = bits
        self.noise_counts_std = noise_counts_std
        self._rng = random.Random(f"firmware_sim/encoder/{seed}")
        self._span = 1 << bits  # wrap_counts, inline in read (the per-period path)
        self._mask = self._span - 1
        self._half = self._span >> 1

    def ideal_counts(self, position: float) -> int:
        """The unwrapped, noise-free count of ``position`` (round half up)."""
        return math.floor(position * self.counts_per_unit + 0.5)

    def read(self, position: float) -> int:
        """The counter value latched at ``position``: rounded, noisy if configured, wrapped.

        Raises ValueError for a position that is not finite or that no count can represent (a
        finite position whose count overflows a float: a runaway plant); the drive reports an
        encoder fault.
        """
        scaled = position * self.counts_per_unit + 0.5
        if scaled - scaled != 0.0:  # NaN or +-inf (math.isfinite without the call)
            raise ValueError(f"encoder position is not finite or beyond any count: {position}")
        counts = math.floor(scaled)
        if self.noise_counts_std > 0.0:
            counts += math.floor(self._rng.gauss(0.0, self.noise_counts_std) + 0.5)
        v = counts & self._mask  # wrap_counts(counts, self.bits)
        return v - self._span if v >= self._half else v
