"""Worst-case bus load (Davis et al. 2007, eq. 2) of the native protocol's cyclic traffic."""

from __future__ import annotations

import dataclasses

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dob_hil.config import DriveConfig
from dob_hil.errors import ConfigError, ProtocolError
from dob_hil.link.busload import check_bus_load, frame_bits, worst_case_bus_load

PAPER_PERIOD_NS = 300_000


@pytest.mark.parametrize(
    ("data_bytes", "extended", "bits"),
    [
        (8, False, 135),  # the classic worst case of an 8-byte standard frame
        (4, False, 95),
        (6, False, 115),  # FEEDBACK
        (3, False, 85),  # COMMAND
        (1, False, 65),  # CONTROL, HEARTBEAT
        (0, False, 55),
        (8, True, 160),  # 29-bit id: g = 54
    ],
)
def test_frame_bits(data_bytes: int, extended: bool, bits: int) -> None:
    assert frame_bits(data_bytes, extended_id=extended) == bits


def stuff_bits(bits: list[int]) -> int:
    """Stuff bits a CAN controller inserts: a complement after 5 equal bits (stuff bits included)."""
    count, run_bit, run = 0, -1, 0
    for b in bits:
        run, run_bit = (run + 1, run_bit) if b == run_bit else (1, b)
        if run == 5:
            count += 1
            run, run_bit = 1, 1 - b  # the stuff bit starts the next run
    return count


@pytest.mark.parametrize("length", range(1, 15))
def test_stuffing_worst_case_by_exhaustion(length: int) -> None:
    """Over every bit string of a short length, the most stuff bits are floor((length - 1) / 4)."""
    worst = max(stuff_bits([(x >> i) & 1 for i in range(length)]) for x in range(2**length))
    assert worst == (length - 1) // 4


@given(n=st.integers(0, 8), extended=st.booleans())
def test_frame_bits_equals_a_simulated_worst_case_frame(n: int, extended: bool) -> None:
    """The g + 8n stuffable bits of the worst pattern 00000 1111 0000 1111 ... plus 13 unstuffed."""
    stuffable = (54 if extended else 34) + 8 * n
    pattern = ([0] * 5 + [1, 1, 1, 1, 0, 0, 0, 0] * 20)[:stuffable]
    assert frame_bits(n, extended_id=extended) == stuffable + stuff_bits(pattern) + 13


@pytest.mark.parametrize("n", [-1, 9, 64])
def test_frame_bits_refuses_impossible_lengths(n: int) -> None:
    with pytest.raises(ProtocolError, match=f"data_bytes: a classic CAN frame carries 0..8 bytes, got {n}"):
        frame_bits(n)


def test_paper_config_loads_the_bus_two_thirds() -> None:
    load = worst_case_bus_load(DriveConfig(), PAPER_PERIOD_NS)
    # FEEDBACK 115 + COMMAND 85 bits per period, a 75-bit heartbeat (2 bytes) every 100 ms
    expected_bits = 115 + 85 + 75 * 10.0 * 300e-6
    assert load.frame_bits == {"FEEDBACK": 115, "COMMAND": 85, "HEARTBEAT": 75}
    assert load.bits_per_period == pytest.approx(expected_bits, rel=1e-12)
    assert load.time_per_period_us == pytest.approx(expected_bits, rel=1e-12)  # 1 bit = 1 us at 1 Mbit/s
    assert load.fraction == pytest.approx(expected_bits / 300.0, rel=1e-12)
    assert 0.66 < load.fraction < 0.67
    assert check_bus_load(DriveConfig(), PAPER_PERIOD_NS) == load
    text = load.breakdown()
    for needle in ("FEEDBACK", "COMMAND", "HEARTBEAT", "66.7%", "1000000 bit/s", "300 us"):
        assert needle in text


def test_impossible_config_is_refused() -> None:
    drive = dataclasses.replace(DriveConfig(), bitrate_bps=250_000)
    with pytest.raises(ConfigError) as info:
        check_bus_load(drive, PAPER_PERIOD_NS)
    assert info.value.field == "drive.bitrate_bps"
    assert "worst-case bus load 267% > 100% at 250000 bit/s and period 300 us" in str(info.value)


def test_a_tighter_budget_can_be_asked_for() -> None:
    with pytest.raises(ConfigError, match="worst-case bus load 67% > 50%"):
        check_bus_load(DriveConfig(), PAPER_PERIOD_NS, max_fraction=0.5)


@given(bitrate=st.integers(10_000, 8_000_000), period_us=st.integers(50, 100_000))
def test_load_scales_with_bit_time_over_period(bitrate: int, period_us: int) -> None:
    drive = dataclasses.replace(DriveConfig(), bitrate_bps=bitrate)
    load = worst_case_bus_load(drive, period_us * 1000, heartbeat_hz=0.0)
    assert load.fraction == pytest.approx(200 / bitrate / (period_us * 1e-6), rel=1e-9)
    if load.fraction > 1.0:
        with pytest.raises(ConfigError):
            check_bus_load(drive, period_us * 1000, heartbeat_hz=0.0)
    else:
        check_bus_load(drive, period_us * 1000, heartbeat_hz=0.0)


def test_bad_period_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"plant\.period_us"):
        worst_case_bus_load(DriveConfig(), 0)
