"""Transport impairments of the drive's outgoing FEEDBACK frames: latency, jitter, loss (seeded).

A frame sampled at ``t`` leaves at ``t + latency + U(0, jitter)`` (uniform), never before the
frame sent before it (a CAN controller keeps its transmit order), unless it is lost, with
probability ``loss_probability``. Loss and jitter draw from separate seeded streams, so changing
one setting does not reshuffle the other.
"""

from __future__ import annotations

import random


class FeedbackImpairment:
    def __init__(self, latency_us: float, jitter_us: float, loss_probability: float, seed: int) -> None:
        if latency_us < 0 or jitter_us < 0 or not 0 <= loss_probability < 1:
            raise ValueError(
                "need latency >= 0, jitter >= 0, 0 <= loss < 1; "
                f"got {latency_us}, {jitter_us}, {loss_probability}"
            )
        self.latency_ns = round(latency_us * 1000.0)
        self.jitter_ns = jitter_us * 1000.0
        self.loss_probability = loss_probability
        self._loss_rng = random.Random(f"firmware_sim/loss/{seed}")
        self._jitter_rng = random.Random(f"firmware_sim/jitter/{seed}")
        self._last_due_ns: int | None = None

    @property
    def delays(self) -> bool:
        return self.latency_ns > 0 or self.jitter_ns > 0

    def lost(self) -> bool:
        """Draw whether the next frame is lost."""
        return self.loss_probability > 0.0 and self._loss_rng.random() < self.loss_probability

    def due_ns(self, ready_ns: int) -> int:
        """When a frame ready at ``ready_ns`` goes out (same clock as ``ready_ns``)."""
        due = ready_ns + self.latency_ns
        if self.jitter_ns > 0:
            due += round(self._jitter_rng.random() * self.jitter_ns)
        if self._last_due_ns is not None and due < self._last_due_ns:
            due = self._last_due_ns
        self._last_due_ns = due
        return due
