"""Encoder counter wrapping (drive side) and unwrapping (host side).

A drive's position counter is ``bits`` wide and wraps. The native FEEDBACK frame carries it in a
signed 32-bit field: for ``bits < 32`` the drive sends the counter sign-extended from ``bits``
(:func:`wrap_counts`), so the value on the wire is in ``-2**(bits-1) .. 2**(bits-1) - 1``.

:class:`CountUnwrapper` turns that sequence back into a continuous position (an unbounded Python
int) by adding the shortest signed difference modulo ``2**bits`` between consecutive samples. It
is exact as long as the true position moves by less than ``2**(bits-1)`` counts between two
samples it is fed (including samples lost on the way); a larger move aliases and cannot be
detected from the counter alone.
"""

from __future__ import annotations

from dob_hil.errors import ConfigError

BITS_MIN = 2
BITS_MAX = 64


def _check_bits(bits: int) -> None:
    if isinstance(bits, bool) or not isinstance(bits, int) or not BITS_MIN <= bits <= BITS_MAX:
        raise ConfigError("drive.encoder_bits", f"must be an integer {BITS_MIN}..{BITS_MAX}, got {bits!r}")


def wrap_counts(value: int, bits: int) -> int:
    """``value`` reduced modulo ``2**bits`` and sign-extended: the counter a ``bits``-wide drive sends."""
    _check_bits(bits)
    half = 1 << (bits - 1)
    return ((value + half) & ((1 << bits) - 1)) - half


class CountUnwrapper:
    """Continuous position in counts from a wrapping ``bits``-wide counter.

    The first sample fed sets the position to that sample (sign-extended); every later sample
    moves it by the shortest signed step modulo ``2**bits``. Any representative of the counter
    modulo ``2**bits`` is accepted (sign-extended or not), so a drive that sends the counter
    unsigned is unwrapped correctly too.
    """

    __slots__ = ("_bits", "_half", "_last", "_mask", "_position")

    def __init__(self, bits: int) -> None:
        _check_bits(bits)
        self._bits = bits
        self._half = 1 << (bits - 1)
        self._mask = (1 << bits) - 1
        self._last: int | None = None
        self._position = 0

    @property
    def bits(self) -> int:
        return self._bits

    @property
    def position(self) -> int | None:
        """The unwrapped position in counts, or None before the first sample."""
        return None if self._last is None else self._position

    def reset(self) -> None:
        """Forget the history: the next sample starts the position afresh."""
        self._last = None
        self._position = 0

    def step(self, raw_counts: int) -> int:
        """The signed step modulo ``2**bits`` from the previous sample (0 for the first one)."""
        last = self._last
        if last is None:
            return 0
        return ((raw_counts - last + self._half) & self._mask) - self._half

    def update(self, raw_counts: int) -> int:
        """Feed one raw counter value; returns the unwrapped position in counts."""
        last = self._last
        if last is None:
            self._position = ((raw_counts + self._half) & self._mask) - self._half
        else:
            self._position += ((raw_counts - last + self._half) & self._mask) - self._half
        self._last = raw_counts
        return self._position

    def update_step(self, raw_counts: int) -> tuple[int, int | None]:
        """:meth:`update` and the unwrapped step it made in one call (the per-sample path):
        (position, position - previous position), the step None for the first sample."""
        last = self._last
        self._last = raw_counts
        if last is None:
            self._position = ((raw_counts + self._half) & self._mask) - self._half
            return self._position, None
        step = ((raw_counts - last + self._half) & self._mask) - self._half
        self._position += step
        return self._position, step
