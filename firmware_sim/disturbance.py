"""Disturbance injected at the plant input: sums of sines, steps and seeded noise, in amperes.

Each ``[[sim.disturbance]]`` entry is zero before its ``start_s`` and then

* ``sine``:  ``amplitude_A * sin(2 pi frequency_hz (t - start_s) + phase_rad)``
* ``step``:  ``amplitude_A``
* ``noise``: Gaussian, standard deviation ``std_A``, one sample per noise interval (the plant's
  sub-step, ``Ts / substeps``), held over that interval. The sample of interval ``i`` depends
  only on ``(seed, i)``, so :meth:`Disturbance.value_A` is a pure function of time: the same
  seed gives the same noise whatever order or rate it is read in.

Time ``t`` is counted from :attr:`Disturbance.origin_s` (default 0); with ``origin_s = None`` the
disturbance is zero everywhere. The drive sets the origin when it is first enabled, so a run starts
from rest whatever clock the drive runs on (PROTOCOL.md leaves disturbances out: they are the
simulation's, not the protocol's).

The paper's disturbances are ``0.2 sin(8 pi t)`` (frequency 4 Hz) and
``0.2 sin(8 pi t) + 0.1 sin(24 pi t)`` (4 Hz and 12 Hz).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from dob_hil.config import DisturbanceConfig

NOISE_BLOCK = 1024  # noise samples generated together from one seeded generator


class _SeededNoise:
    """Held Gaussian noise: sample ``i`` is element ``i % NOISE_BLOCK`` of block ``i // NOISE_BLOCK``."""

    def __init__(self, std_A: float, seed: int, interval_s: float, start_s: float) -> None:
        self.std_A = std_A
        self.seed = seed
        self.interval_s = interval_s
        self.start_s = start_s
        self._block_index: int | None = None
        self._block: list[float] = []

    def sample_A(self, index: int) -> float:
        """Sample ``index`` (>= 0)."""
        block, offset = divmod(index, NOISE_BLOCK)
        if block != self._block_index:
            rng = np.random.default_rng([self.seed, block])
            self._block = (rng.standard_normal(NOISE_BLOCK) * self.std_A).tolist()
            self._block_index = block
        return self._block[offset]

    def value_A(self, t_s: float) -> float:
        if t_s < self.start_s:
            return 0.0
        return self.sample_A(math.floor(t_s / self.interval_s))

    def values_A(self, t_s: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """:meth:`value_A` at every element (0 before ``start_s``: a time before the origin, once
        the origin has moved, has no sample to draw)."""
        out = np.zeros(t_s.shape, dtype=np.float64)
        on = t_s >= self.start_s
        index = np.floor(t_s[on] / self.interval_s).astype(np.int64)
        out[on] = [self.sample_A(int(i)) for i in index]
        return out


class Disturbance:
    """The sum of the configured disturbances; ``value_A(t_s)`` is the current added at the plant input."""

    def __init__(self, entries: Sequence[DisturbanceConfig], noise_interval_s: float) -> None:
        if not noise_interval_s > 0:
            raise ValueError(f"noise_interval_s must be > 0, got {noise_interval_s}")
        self.entries = tuple(entries)
        self.noise_interval_s = noise_interval_s
        # (amplitude, angular frequency, phase at t = 0 of the shifted sine, start)
        self._sines: list[tuple[float, float, float, float]] = []
        self._steps: list[tuple[float, float]] = []
        self._noises: list[_SeededNoise] = []
        for e in self.entries:
            if e.kind == "sine":
                if e.amplitude_A != 0.0:
                    w = 2.0 * math.pi * e.frequency_hz
                    self._sines.append((e.amplitude_A, w, e.phase_rad - w * e.start_s, e.start_s))
            elif e.kind == "step":
                if e.amplitude_A != 0.0:
                    self._steps.append((e.amplitude_A, e.start_s))
            elif e.kind == "noise":
                if e.std_A > 0.0:
                    self._noises.append(_SeededNoise(e.std_A, e.seed, noise_interval_s, e.start_s))
            else:
                raise ValueError(f"unknown disturbance kind {e.kind!r}")
        self.is_zero = not (self._sines or self._steps or self._noises)
        self.origin_s: float | None = 0.0  # t = 0 of every entry, in the caller's seconds
        if len(self._sines) == 1 and not (self._steps or self._noises):
            # the common case (one per-period call of a lockstep drive's ground truth)
            self._sine = self._sines[0]
            self.value_A = self._value_one_sine  # type: ignore[method-assign]

    def value_A(self, t_s: float) -> float:
        """The disturbance current at time ``t_s`` (seconds of the caller's clock; see origin_s)."""
        origin = self.origin_s
        if origin is None:
            return 0.0
        if origin:
            t_s -= origin
        v = 0.0
        for a, w, p, start in self._sines:
            if t_s >= start:
                v += a * math.sin(w * t_s + p)
        for a, start in self._steps:
            if t_s >= start:
                v += a
        for n in self._noises:
            v += n.value_A(t_s)
        return v

    def _value_one_sine(self, t_s: float) -> float:
        """:meth:`value_A` of a disturbance that is one sine: the same arithmetic, bit for bit
        (``0.0 +`` as the sum's start: a sine of -0.0 gives 0.0, as there)."""
        origin = self.origin_s
        if origin is None:
            return 0.0
        if origin:
            t_s -= origin
        a, w, p, start = self._sine
        if t_s >= start:
            return 0.0 + a * math.sin(w * t_s + p)
        return 0.0

    def values_A(self, t_s: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """:meth:`value_A` at every element of ``t_s`` (vectorised; equal to within rounding)."""
        t = np.asarray(t_s, dtype=np.float64)
        v = np.zeros_like(t)
        if self.origin_s is None:
            return v
        if self.origin_s:
            t = t - self.origin_s
        for a, w, p, start in self._sines:
            v += np.where(t >= start, a * np.sin(w * t + p), 0.0)
        for a, start in self._steps:
            v += np.where(t >= start, a, 0.0)
        for n in self._noises:
            v += n.values_A(t)
        return v
