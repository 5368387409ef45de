"""Percentiles of integer nanosecond values in bounded memory, streamed block by block.

:class:`IntCounts` keeps every distinct value with its count (sorted). Its percentiles are those
of :func:`numpy.percentile` (method "linear") of all the values, bit for bit: the two order
statistics around the virtual index ``(n - 1) q`` are found in the cumulative counts and
interpolated with numpy's own formula. Memory grows with the number of *distinct* values, not
with the number of values: timing values of a run spread over a few thousand to a few hundred
thousand nanosecond values (16 B each). Should more than :data:`MAX_DISTINCT` distinct values arrive, every
value (those held and those to come) is rounded down to :data:`COARSE_BITS` significant bits
(relative error below 2**-11, a histogram with log-linear bins), which bounds the distinct
values to about 12 bits x 64 exponents; :attr:`IntCounts.method` then says so.
"""

from __future__ import annotations

from typing import Final

import numpy as np
import numpy.typing as npt

MAX_DISTINCT: Final = 1 << 18
COARSE_BITS: Final = 12
EXACT: Final = "exact"
COARSE: Final = f"values rounded down to {COARSE_BITS} significant bits"

IntArray = npt.NDArray[np.int64]


def _coarsen(values: IntArray) -> IntArray:
    """Non-negative values rounded down to COARSE_BITS significant bits."""
    v = np.asarray(values, dtype=np.int64)
    bits = np.zeros(len(v), dtype=np.int64)
    big = v >= (1 << COARSE_BITS)
    if big.any():
        bits[big] = np.floor(np.log2(v[big].astype(np.float64))).astype(np.int64) + 1
        # float log2 may be one off near powers of two: fix by checking the bounds
        bits[big] += (v[big] >> np.minimum(bits[big], 62)) > 0
        bits[big] -= (v[big] >> np.maximum(bits[big] - 1, 0)) == 0
    drop = np.maximum(bits - COARSE_BITS, 0)
    return (v >> drop) << drop


class IntCounts:
    """The distribution of non-negative integers added block by block (module docstring)."""

    def __init__(self) -> None:
        self.values = np.zeros(0, dtype=np.int64)  # sorted distinct values
        self.counts = np.zeros(0, dtype=np.int64)
        self.coarse = False

    @property
    def n(self) -> int:
        return int(self.counts.sum())

    @property
    def method(self) -> str:
        return COARSE if self.coarse else EXACT

    def add(self, block: npt.ArrayLike) -> None:
        v = np.asarray(block).astype(np.int64, copy=False)
        if len(v) == 0:
            return
        if self.coarse:
            v = _coarsen(v)
        keys, counts = np.unique(v, return_counts=True)
        if len(self.values) == 0:
            self.values, self.counts = keys, counts.astype(np.int64)
        else:  # merge in place where the value is known, insert the new ones
            at = np.searchsorted(self.values, keys)
            known = at < len(self.values)
            known[known] = self.values[at[known]] == keys[known]
            np.add.at(self.counts, at[known], counts[known])
            new = ~known
            if new.any():
                self.values = np.insert(self.values, at[new], keys[new])
                self.counts = np.insert(self.counts, at[new], counts[new])
        if len(self.values) > MAX_DISTINCT:
            self.coarse = True
            coarse, inverse = np.unique(_coarsen(self.values), return_inverse=True)
            self.counts = np.bincount(inverse, weights=self.counts, minlength=len(coarse)).astype(np.int64)
            self.values = coarse

    def order_statistics(self, ranks: IntArray) -> IntArray:
        """The values at 0-based positions ``ranks`` of the sorted values."""
        ends = np.cumsum(self.counts)
        return self.values[np.searchsorted(ends, np.asarray(ranks, dtype=np.int64), side="right")]

    def percentiles(self, q_percent: list[float], scale: float = 1.0) -> list[float]:
        """``numpy.percentile(values * scale, q_percent)`` (method "linear"), bit for bit."""
        n = self.n
        q = np.true_divide(np.asarray(q_percent, dtype=np.float64), 100)
        virtual = (n - 1) * q
        previous = np.floor(virtual)
        following = previous + 1
        above = virtual >= n - 1
        previous[above] = n - 1
        following[above] = n - 1
        gamma = np.asanyarray(virtual - previous, dtype=virtual.dtype)
        gamma[above] = 0.0
        a = self.order_statistics(previous.astype(np.int64)).astype(np.float64) * scale
        b = self.order_statistics(following.astype(np.int64)).astype(np.float64) * scale
        diff = b - a
        out = np.add(a, diff * gamma)
        np.subtract(b, diff * (1 - gamma), out=out, where=gamma >= 0.5)
        return [float(x) for x in out]

    def distribution(self, scale: float = 1.0) -> dict[str, float | int] | None:
        """As :func:`dob_hil.analysis.metrics.distribution` of all the values added."""
        n = self.n
        if n == 0:
            return None
        p50, p99 = self.percentiles([50.0, 99.0], scale)
        return {"p50": p50, "p99": p99, "max": float(self.values[-1].astype(np.float64) * scale), "n": n}

    def median(self) -> float:
        """``numpy.median`` of the values (the mean of the two middle ones for an even count)."""
        n = self.n
        lo, hi = self.order_statistics(np.asarray([(n - 1) // 2, n // 2], dtype=np.int64))
        return float(np.mean(np.asarray([lo, hi], dtype=np.int64)))
