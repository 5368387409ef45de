"""The drive's parts on their own: DAC, encoder, disturbance, state machine, watchdog, current path."""

from __future__ import annotations

import math
import statistics

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from dob_hil.config import DisturbanceConfig
from dob_hil.link.protocol import ControlRequest, DriveState, FaultCode
from firmware_sim.actuator import CurrentPath
from firmware_sim.dac import Dac
from firmware_sim.disturbance import Disturbance
from firmware_sim.encoder import Encoder, wrap_counts
from firmware_sim.impairments import FeedbackImpairment
from firmware_sim.state_machine import TRANSITIONS, DriveStateMachine
from firmware_sim.watchdog import CommandWatchdog


# --- DAC ------------------------------------------------------------------------------------------
def test_dac_limit_code_and_saturation() -> None:
    dac = Dac(1.0 / 2048.0, 0.7)
    assert dac.limit_counts == 1433  # floor(0.7 * 2048) = floor(1433.6)
    assert dac.convert(1433) == (1433, 1433 / 2048, False)
    assert dac.convert(1434) == (1433, 1433 / 2048, True)
    assert dac.convert(-32768) == (-1433, -1433 / 2048, True)
    assert dac.convert(-1433) == (-1433, -1433 / 2048, False)
    assert dac.convert(0) == (0, 0.0, False)


def test_dac_limit_exactly_on_a_code() -> None:
    # 0.5 A at 1/2048 A is exactly code 1024; a float quotient just below must not lose it
    assert Dac(1.0 / 2048.0, 0.5).limit_counts == 1024
    assert Dac(0.1, 0.3).limit_counts == 3  # 0.3 / 0.1 = 2.9999999999999996


@given(st.integers(-32768, 32767))
def test_dac_applied_current_is_code_times_lsb_within_the_limit(counts: int) -> None:
    dac = Dac(1.0 / 2048.0, 0.7)
    code, applied, saturated = dac.convert(counts)
    assert abs(code) <= 1433 and applied == code / 2048
    assert saturated == (code != counts)
    assert saturated == (abs(counts) > 1433)


# --- encoder --------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("position", "counts"),
    [(0.0, 0), (1.0, 10000), (0.00005, 1), (0.000049, 0), (-0.00005, 0), (-0.000051, -1), (-1.23456, -12346)],
)
def test_encoder_rounds_half_up(position: float, counts: int) -> None:
    enc = Encoder(10000.0, 32)
    assert enc.read(position) == counts == math.floor(position * 10000 + 0.5)


@pytest.mark.parametrize(
    ("bits", "counts", "wrapped"),
    [
        (16, 32767, 32767),
        (16, 32768, -32768),
        (16, 65535, -1),
        (16, 65536, 0),
        (16, -32769, 32767),
        (8, 200, -56),
        (32, 2**31, -(2**31)),
        (24, 2**23 + 5, -(2**23) + 5),
    ],
)
def test_wrap_counts(bits: int, counts: int, wrapped: int) -> None:
    assert wrap_counts(counts, bits) == wrapped


@given(st.integers(-(2**40), 2**40), st.integers(8, 32))
def test_wrap_is_the_twos_complement_residue(counts: int, bits: int) -> None:
    w = wrap_counts(counts, bits)
    assert -(2 ** (bits - 1)) <= w < 2 ** (bits - 1)
    assert (w - counts) % (2**bits) == 0


def test_encoder_wraps_at_its_width() -> None:
    enc = Encoder(10000.0, 16)
    assert enc.read(3.2767) == 32767
    assert enc.read(3.2768) == -32768
    assert enc.read(-3.2769) == 32767


def test_encoder_noise_is_seeded_and_has_the_configured_spread() -> None:
    a = [Encoder(10000.0, 32, 3.0, seed=5).read(1.0) for _ in range(1)]
    enc1, enc2, enc3 = (
        Encoder(10000.0, 32, 3.0, 5),
        Encoder(10000.0, 32, 3.0, 5),
        Encoder(10000.0, 32, 3.0, 6),
    )
    r1 = [enc1.read(1.0) - 10000 for _ in range(4000)]
    r2 = [enc2.read(1.0) - 10000 for _ in range(4000)]
    r3 = [enc3.read(1.0) - 10000 for _ in range(4000)]
    assert r1 == r2 and r1 != r3 and a[0] - 10000 == r1[0]
    assert all(isinstance(v, int) for v in r1)
    assert abs(statistics.fmean(r1)) < 0.3
    assert 2.8 < statistics.pstdev(r1) < 3.2  # rounding adds 1/12 count^2 of variance


def test_encoder_refuses_a_non_finite_position() -> None:
    with pytest.raises(ValueError, match="not finite"):
        Encoder(10000.0, 32).read(float("nan"))


# --- disturbance ------------------------------------------------------------------------------------
def sine(amplitude: float, freq: float, phase: float = 0.0, start: float = 0.0) -> DisturbanceConfig:
    return DisturbanceConfig("sine", amplitude_A=amplitude, frequency_hz=freq, phase_rad=phase, start_s=start)


@pytest.mark.parametrize("t", [0.0, 0.01, 0.0625, 0.1, 0.337, 1.0])
def test_paper_disturbances(t: float) -> None:
    d1 = Disturbance([sine(0.2, 4.0)], 30e-6)
    d2 = Disturbance([sine(0.2, 4.0), sine(0.1, 12.0)], 30e-6)
    assert d1.value_A(t) == pytest.approx(0.2 * math.sin(8 * math.pi * t), abs=1e-15)
    expected = 0.2 * math.sin(8 * math.pi * t) + 0.1 * math.sin(24 * math.pi * t)
    assert d2.value_A(t) == pytest.approx(expected, abs=1e-15)


def test_sine_phase_and_start_and_step() -> None:
    d = Disturbance(
        [
            sine(0.5, 2.0, phase=math.pi / 2, start=0.25),
            DisturbanceConfig("step", amplitude_A=-0.1, start_s=0.5),
        ],
        30e-6,
    )
    assert d.value_A(0.2) == 0.0
    assert d.value_A(0.25) == pytest.approx(0.5)  # starts at its phase: sin(pi/2)
    assert d.value_A(0.375) == pytest.approx(0.5 * math.sin(2 * math.pi * 2 * 0.125 + math.pi / 2))
    assert d.value_A(0.5) == pytest.approx(0.5 * math.sin(2 * math.pi * 2 * 0.25 + math.pi / 2) - 0.1)  # -0.6
    assert not d.is_zero and Disturbance([sine(0.0, 4.0)], 1e-3).is_zero


def test_noise_is_seeded_held_per_interval_and_pure() -> None:
    cfg = DisturbanceConfig("noise", std_A=0.05, seed=11)
    d1, d2 = Disturbance([cfg], 1e-4), Disturbance([cfg], 1e-4)
    other = Disturbance([DisturbanceConfig("noise", std_A=0.05, seed=12)], 1e-4)
    t = np.arange(20000) * 1e-4 + 3e-5
    forward = [d1.value_A(float(x)) for x in t]
    backward = [d2.value_A(float(x)) for x in t[::-1]][::-1]  # order of reading does not matter
    assert forward == backward
    assert forward != [other.value_A(float(x)) for x in t]
    assert d1.value_A(0.5e-4) == d1.value_A(0.9e-4)  # held over one interval
    assert statistics.pstdev(forward) == pytest.approx(0.05, rel=0.03)
    assert abs(statistics.fmean(forward)) < 0.002


def test_vectorised_values_equal_the_scalar_function() -> None:
    d = Disturbance(
        [
            sine(0.2, 4.0),
            sine(0.1, 12.0, 0.3, 0.01),
            DisturbanceConfig("step", amplitude_A=0.05, start_s=0.02),
            DisturbanceConfig("noise", std_A=0.01, seed=2, start_s=0.005),
        ],
        30e-6,
    )
    t = (np.arange(5000) + 0.5) * 30e-6
    np.testing.assert_allclose(d.values_A(t), [d.value_A(float(x)) for x in t], rtol=0, atol=1e-15)


# --- state machine and watchdog ---------------------------------------------------------------------
@pytest.mark.parametrize("state", list(DriveState))
@pytest.mark.parametrize("request_", list(ControlRequest))
def test_state_machine_table(state: DriveState, request_: ControlRequest) -> None:
    sm = DriveStateMachine()
    if state is DriveState.ENABLED:
        sm.request(ControlRequest.ENABLE)
    elif state is DriveState.FAULT:
        sm.fault(FaultCode.WATCHDOG)
    assert sm.state is state
    new = sm.request(request_)
    expected = {
        (DriveState.DISABLED, ControlRequest.ENABLE): DriveState.ENABLED,
        (DriveState.ENABLED, ControlRequest.DISABLE): DriveState.DISABLED,
        (DriveState.FAULT, ControlRequest.CLEAR_FAULT): DriveState.DISABLED,
    }.get((state, request_), state)
    assert new is expected is sm.state
    assert TRANSITIONS.get((state, request_), state) is expected
    assert (sm.fault_code is None) == (sm.state is not DriveState.FAULT)


def test_fault_keeps_the_first_code() -> None:
    sm = DriveStateMachine()
    assert sm.fault(FaultCode.BAD_FRAME)
    assert not sm.fault(FaultCode.WATCHDOG)
    assert sm.fault_code is FaultCode.BAD_FRAME and sm.state is DriveState.FAULT


def test_watchdog_trips_on_the_nth_missed_period_once_armed() -> None:
    wd = CommandWatchdog(3)
    assert [wd.period_elapsed(False) for _ in range(2)] == [False, False]
    assert not wd.period_elapsed(True) and wd.missed == 0  # a command arms it and resets the count
    assert [wd.period_elapsed(False) for _ in range(3)] == [False, False, True]
    assert wd.missed == 3 and wd.info == 3


def test_watchdog_before_the_first_command_allows_the_arming_time() -> None:
    wd = CommandWatchdog(3, arm_periods=10)
    assert [wd.period_elapsed(False) for _ in range(10)] == [False] * 9 + [True]
    assert wd.info == 0  # no first command
    wd = CommandWatchdog(3)  # at least twice the watchdog
    assert [wd.period_elapsed(False) for _ in range(6)] == [False] * 5 + [True]
    wd.reset()  # entering ENABLED again: disarmed
    assert not wd.armed and [wd.period_elapsed(False) for _ in range(5)] == [False] * 5


# --- current path (input delay) --------------------------------------------------------------------
def test_current_path_orders_changes_and_cut_drops_later_ones() -> None:
    path = CurrentPath()
    path.schedule(300, 0.3)
    path.schedule(100, 0.1)
    path.schedule(200, 0.2)
    assert path.next_change_ns() == 100
    path.apply_due(150)
    assert path.held_A == 0.1 and path.next_change_ns() == 200
    path.cut(250)  # 0.2 at 200 still happens; 0.3 at 300 never does
    path.apply_due(1000)
    assert path.held_A == 0.0 and path.pending == 0
    path.schedule(500, 0.5)
    path.apply_due(499)
    assert path.held_A == 0.0
    path.apply_due(500)
    assert path.held_A == 0.5


# --- impairments ----------------------------------------------------------------------------------
def test_impairments_are_seeded_and_keep_frame_order() -> None:
    a = FeedbackImpairment(100.0, 250.0, 0.2, seed=9)
    b = FeedbackImpairment(100.0, 250.0, 0.2, seed=9)
    lost_a = [a.lost() for _ in range(2000)]
    assert lost_a == [b.lost() for _ in range(2000)]
    assert 0.15 < sum(lost_a) / 2000 < 0.25
    dues = [a.due_ns(k * 300_000) for k in range(2000)]
    assert dues == [b.due_ns(k * 300_000) for k in range(2000)]
    assert dues == sorted(dues)
    delays = [d - k * 300_000 for k, d in enumerate(dues)]
    assert min(delays) >= 100_000 and max(delays) <= 350_000
    assert FeedbackImpairment(0.0, 0.0, 0.0, 0).lost() is False


@given(
    st.floats(-2.0, 2.0),
    st.floats(0.0, 50.0),
    st.floats(-4.0, 4.0),
    st.floats(0.0, 0.5),
    st.one_of(st.none(), st.floats(-1.0, 1.0)),
    st.lists(st.floats(-1.0, 3.0), min_size=1, max_size=20),
)
def test_one_sine_value_is_the_general_sum_bit_for_bit(
    amplitude: float, hz: float, phase: float, start: float, origin: float | None, times: list[float]
) -> None:
    """A disturbance of one sine takes a shorter value_A (the per-period path): the same bits."""
    one = Disturbance([sine(amplitude, hz, phase=phase, start=start)], 30e-6)
    if amplitude == 0.0:
        assert one.is_zero
        return
    assert one.value_A == one._value_one_sine
    general = Disturbance.value_A.__get__(one)  # the class's sum over every entry
    one.origin_s = origin
    for t in [*times, start, -0.0, math.nextafter(start, -math.inf)]:
        fast, slow = one.value_A(t), general(t)
        assert (fast, math.copysign(1.0, fast)) == (slow, math.copysign(1.0, slow))  # -0.0 too
