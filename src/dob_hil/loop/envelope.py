"""The safety envelope: limits on what the loop observes that trip a safe stop, and the encoder check.

``[safety]`` config section (every key optional)::

    max_abs_position = 5.0          # |y| of every output, plant output units
    position_window = [-1.0, 3.0]   # or a window [low, high] for every output
    max_abs_velocity = 200.0        # |dy/dt| estimated from successive measured positions, units/s
    max_tracking_error = 0.5        # |C x_ref - y| of every output, units
    max_encoder_jumps = 0           # ENCODER_JUMP events tolerated (more trips the envelope)

Defaults: no position or tracking limit; ``max_abs_velocity`` the speed at which the encoder moves a
quarter of its counter range in one period (the link flags such a step as an encoder jump, and at
half the range the unwrapping aliases); ``max_encoder_jumps = 0``. A non-finite measured position
always trips. A trip sets the run's stop reason to ``safety envelope: <what>``: the runner stops at
the next sample, the session commands zero current, disables the drive, finalises the log and
raises :class:`SafetyTrip` (a :class:`~dob_hil.errors.DriveFault`: one line, non-zero exit).

:func:`check_encoder_resolution` refuses, before anything is enabled, an encoder that would alias at
the speed the plant reaches at the current limit within the run (an 8-bit encoder at 10000 counts
per unit aliases above 43 units/s, and the paper's plant reaches 117 units/s at 0.7 A).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from dob_hil.errors import ConfigError, DriveFault

if TYPE_CHECKING:
    from dob_hil.config import Config, ConfigSection

MAX_STEPS = 4_000  # intervals of the speed bound's integral (a fine grid, bounded cost: ~10 ms)


class SafetyTrip(DriveFault):
    """The run left its safety envelope (the message is the reason: ``safety envelope: ...``)."""


@dataclass(frozen=True)
class SafetyConfig:
    """The ``[safety]`` section. ``None``: that limit is off (``max_abs_velocity``: derived)."""

    max_abs_position: float | None = None
    position_window: tuple[float, float] | None = None
    max_abs_velocity: float | None = None
    max_tracking_error: float | None = None
    max_encoder_jumps: int = 0


def parse_safety(s: ConfigSection) -> SafetyConfig:
    """The ``[safety]`` table (``s``), validated; ConfigError names the key."""
    max_pos = s.optional_number("max_abs_position", positive=True)
    window = s.numbers("position_window")
    if window is not None and (len(window) != 2 or not window[0] < window[1]):
        raise ConfigError(
            s.name("position_window"), f"expected [low, high] with low < high, got {list(window)}"
        )
    max_vel = s.optional_number("max_abs_velocity", positive=True)
    max_err = s.optional_number("max_tracking_error", positive=True)
    jumps = s.integer("max_encoder_jumps", 0, low=0, high=1_000_000_000)
    s.finish()
    return SafetyConfig(max_pos, None if window is None else (window[0], window[1]), max_vel, max_err, jumps)


def encoder_jump_speed(config: Config) -> float:
    """Output speed (units/s) at which the encoder moves a quarter of its counter range per period."""
    drive = config.drive
    return float(2 ** (drive.encoder_bits - 2) / (drive.encoder_counts_per_unit * config.plant.period_s))


def max_output_speed(config: Config, horizon_s: float) -> np.ndarray:
    """Upper bound of |dy/dt| per output the plant reaches from rest within ``horizon_s`` with every
    input anywhere in +-``drive.current_limit_A``: ``limit * (sum_j |C_i B_j| + int_0^T |h_ij|)`` with
    the speed's impulse response ``h(t) = C A e^(At) B``. The integral is summed over intervals dt
    as ``|C (e^(A dt) - I) e^(A k dt) B|`` (exact per interval where h keeps its sign in it)."""
    from scipy.linalg import expm

    p = config.plant
    A, B, C = p.A, p.B, p.C
    n_steps = max(1, min(MAX_STEPS, math.ceil(horizon_s / p.period_s)))
    dt = horizon_s / n_steps
    with np.errstate(all="ignore"):
        Phi = expm(A * dt)
        D = C @ (Phi - np.eye(A.shape[0]))
        total = np.abs(C @ B)  # the direct term (outputs x inputs)
        v = B.copy()
        for _ in range(n_steps):
            total += np.abs(D @ v)
            v = Phi @ v
    speed: np.ndarray = config.drive.current_limit_A * total.sum(axis=1)
    return np.where(np.isfinite(speed), speed, math.inf)


def check_encoder_resolution(config: Config, horizon_s: float) -> None:
    """ConfigError (naming ``drive.encoder_bits``) if the plant can move the encoder by more than a
    quarter of its range in one period at the current limit within ``horizon_s``.

    An open-loop unstable plant (an eigenvalue of A in the right half plane) has no such bound (at
    the limit it runs away); it is not refused here: the run-time envelope's velocity limit
    (by default this same speed) stops a run that gets there."""
    if float(np.max(np.linalg.eigvals(config.plant.A).real)) > 0.0:
        return
    bound = encoder_jump_speed(config)
    speed = float(np.max(max_output_speed(config, horizon_s)))
    if not speed < bound:
        d = config.drive
        raise ConfigError(
            "drive.encoder_bits",
            f"a {d.encoder_bits}-bit encoder at {d.encoder_counts_per_unit:g} counts per unit moves a "
            f"quarter of its range per {config.plant.period_ns / 1000:g} us period above {bound:.4g} "
            f"{config.plant.output_unit}/s (and aliases at twice that), but the plant reaches "
            f"{speed:.4g} {config.plant.output_unit}/s at the current limit of "
            f"{d.current_limit_A:g} A within {horizon_s:g} s: use more encoder bits or fewer counts per unit",
        )


class Envelope:
    """The run-time check: :meth:`check` per measured sample, :meth:`encoder_jump` per event. A trip
    calls ``trip(reason)`` once (the session sets the run's stop reason with it)."""

    def __init__(
        self,
        safety: SafetyConfig,
        *,
        C_rows: tuple[tuple[float, ...], ...],
        period_ns: int,
        default_max_velocity: float,
        trip: Callable[[str], None],
    ) -> None:
        low, high = -math.inf, math.inf
        if safety.max_abs_position is not None:
            low, high = -safety.max_abs_position, safety.max_abs_position
        if safety.position_window is not None:
            low, high = max(low, safety.position_window[0]), min(high, safety.position_window[1])
        self._low, self._high = low, high
        self._max_vel = (
            safety.max_abs_velocity if safety.max_abs_velocity is not None else default_max_velocity
        )
        self._max_err = safety.max_tracking_error if safety.max_tracking_error is not None else math.inf
        self._max_jumps = safety.max_encoder_jumps
        self._C_rows = C_rows
        self._period_s = period_ns * 1e-9
        self._trip = trip
        self._prev: tuple[float, ...] | None = None
        self._prev_k = 0
        self.jumps = 0
        self.reason: str | None = None
        if len(C_rows) == 1 and self._max_err == math.inf:
            self.check = self._check_one  # type: ignore[method-assign]  # the common case, kept short

    def _check_one(self, k: int, position: tuple[float, ...], x_ref: tuple[float, ...]) -> None:
        """:meth:`check` for one output and no tracking limit (same verdicts, fewer steps)."""
        y = position[0]
        prev, prev_k = self._prev, self._prev_k
        self._prev, self._prev_k = position, k
        if self._low <= y <= self._high and y - y == 0.0:
            if prev is None:
                return
            dk = k - prev_k
            if dk == 1:
                v = (y - prev[0]) / self._period_s
            elif dk > 1:
                v = (y - prev[0]) / (dk * self._period_s)
            else:
                return
            if -self._max_vel <= v <= self._max_vel:
                return
        self._prev = prev  # the full check names what was wrong
        self._prev_k = prev_k
        Envelope.check(self, k, position, x_ref)

    def _fail(self, reason: str) -> None:
        if self.reason is None:
            self.reason = f"safety envelope: {reason}"
            self._trip(self.reason)

    def encoder_jump(self) -> None:
        self.jumps += 1
        if self.jumps > self._max_jumps:
            self._fail(
                f"{self.jumps} encoder jump(s), at most {self._max_jumps} allowed (safety.max_encoder_jumps)"
            )

    def check(self, k: int, position: tuple[float, ...], x_ref: tuple[float, ...]) -> None:
        """Sample ``k``'s measured output against the limits (cheap: a few comparisons per output)."""
        prev, prev_k = self._prev, self._prev_k
        self._prev, self._prev_k = position, k
        for i, y in enumerate(position):
            if not self._low <= y <= self._high or y - y != 0.0:  # y - y: NaN for NaN and +-inf
                if y - y != 0.0:
                    self._fail(f"non-finite position {y} (output {i}) at sample {k}")
                else:
                    self._fail(
                        f"position {y:.6g} (output {i}) outside [{self._low:g}, {self._high:g}] at sample {k}"
                    )
                return
            if prev is not None and k > prev_k:
                v = (y - prev[i]) / ((k - prev_k) * self._period_s)
                if not -self._max_vel <= v <= self._max_vel:
                    self._fail(
                        f"velocity estimate {v:.6g}/s (output {i}) beyond {self._max_vel:.6g}/s at sample {k}"
                    )
                    return
            if self._max_err != math.inf:
                err = sum(c * x for c, x in zip(self._C_rows[i], x_ref, strict=False)) - y
                if not -self._max_err <= err <= self._max_err:
                    self._fail(
                        f"tracking error {err:.6g} (output {i}) beyond {self._max_err:g} at sample {k}"
                    )
                    return
