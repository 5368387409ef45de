"""Encoder counter wrapping and unwrapping."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dob_hil.errors import ConfigError
from dob_hil.link.unwrap import CountUnwrapper, wrap_counts


@pytest.mark.parametrize("bits", [12, 16, 32])
def test_wrap_counts_is_the_sign_extended_counter(bits: int) -> None:
    half = 2 ** (bits - 1)
    assert wrap_counts(0, bits) == 0
    assert wrap_counts(half - 1, bits) == half - 1
    assert wrap_counts(half, bits) == -half
    assert wrap_counts(-half - 1, bits) == half - 1
    assert wrap_counts(2**bits + 5, bits) == 5
    assert wrap_counts(-1, bits) == -1


@given(value=st.integers(-(2**70), 2**70), bits=st.integers(2, 64))
def test_wrap_counts_range_and_congruence(value: int, bits: int) -> None:
    w = wrap_counts(value, bits)
    assert -(2 ** (bits - 1)) <= w < 2 ** (bits - 1)
    assert (w - value) % 2**bits == 0


@pytest.mark.parametrize("bits", [32, 16, 12])
@pytest.mark.parametrize("direction", [+1, -1])
def test_unwrap_across_the_rollover(bits: int, direction: int) -> None:
    half = 2 ** (bits - 1)
    start = half - 3 if direction > 0 else -half + 3
    u = CountUnwrapper(bits)
    positions = [start + direction * k * 2 for k in range(6)]  # crosses +-2**(bits-1) after 2 samples
    raw = [wrap_counts(x, bits) for x in positions]
    assert any(r * raw[0] < 0 for r in raw)  # the raw counter did jump sign
    assert [u.update(r) for r in raw] == positions
    assert u.position == positions[-1]


def test_unwrap_several_turns_and_back() -> None:
    u = CountUnwrapper(12)
    step = 1500  # < 2048 = 2**11
    up = [k * step for k in range(20)]
    down = [up[-1] - k * step for k in range(1, 40)]
    assert [u.update(wrap_counts(x, 12)) for x in up + down] == up + down


def test_first_sample_is_taken_as_it_is_and_reset_restarts() -> None:
    u = CountUnwrapper(16)
    assert u.position is None
    assert u.step(123) == 0
    assert u.update(-7) == -7
    assert u.step(-9) == -2
    assert u.update(65535 - 8) == -9  # an unsigned representative of -9 is understood too
    u.reset()
    assert u.position is None
    assert u.update(100) == 100


@st.composite
def random_walks(draw: st.DrawFn) -> tuple[int, int, list[int]]:
    bits = draw(st.sampled_from([8, 12, 16, 24, 32]))
    bound = 2 ** (bits - 1) - 1
    start = draw(st.integers(-(2 ** (bits - 1)), 2 ** (bits - 1) - 1))
    steps = draw(st.lists(st.integers(-bound, bound), max_size=200))
    return bits, start, steps


@given(walk=random_walks())
def test_unwrapped_equals_true_position_on_a_bounded_random_walk(walk: tuple[int, int, list[int]]) -> None:
    bits, start, steps = walk
    u = CountUnwrapper(bits)
    position = start
    assert u.update(wrap_counts(position, bits)) == position
    for d in steps:
        position += d
        assert u.update(wrap_counts(position, bits)) == position


@pytest.mark.parametrize("bits", [0, 1, 65, True, 16.0])
def test_bad_width_is_a_config_error(bits: object) -> None:
    with pytest.raises(ConfigError, match=r"drive\.encoder_bits"):
        CountUnwrapper(bits)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=r"drive\.encoder_bits"):
        wrap_counts(0, bits)  # type: ignore[arg-type]


@given(raw=st.lists(st.integers(-(2**31), 2**31 - 1), min_size=1, max_size=50), bits=st.integers(2, 32))
def test_update_step_is_update_and_the_step_it_made(raw: list[int], bits: int) -> None:
    one, two = CountUnwrapper(bits), CountUnwrapper(bits)
    for value in raw:
        counter = wrap_counts(value, bits)
        before = one.position
        position = one.update(counter)
        assert two.update_step(counter) == (position, None if before is None else position - before)
        assert two.position == one.position
