"""The analysis's numerical pieces by property: model output, decimation, the DAC quantizer."""

from __future__ import annotations

import math
from fractions import Fraction

import can
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dob_hil.analysis.downsample import envelope_indices
from dob_hil.analysis.model import nominal_output
from dob_hil.config import DriveConfig, load_config
from dob_hil.design import build_design
from dob_hil.link.native import DacQuantizer, NativeDriveLink
from dob_hil.scenarios import scenario_path


@pytest.fixture(scope="module")
def design():  # type: ignore[no-untyped-def]
    return build_design(load_config(scenario_path("paper-sine")))


def _reference(n: int, period_s: float) -> np.ndarray:
    t = np.arange(n) * period_s
    w = 2 * np.pi
    return np.stack([0.01 * np.sin(w * t), 0.01 * w * np.cos(w * t)], axis=1)


def _closed_loop(design, x_ref: np.ndarray, limit: float) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Independent: with an exact estimator u = sat(Kc (r - x)), x' = Phi x + Gam u, y = C x."""
    x = np.zeros(design.n_states)
    y = np.empty((len(x_ref), design.n_outputs))
    for k, r in enumerate(x_ref):
        y[k] = design.C @ x
        u = np.clip(design.Kc @ (r - x), -limit, limit)
        x = design.Phi @ x + design.Gam @ u
    return y


@pytest.mark.parametrize("limit", [math.inf, 0.7])
def test_model_output_is_the_nominal_state_feedback_loop(design, limit: float) -> None:  # type: ignore[no-untyped-def]
    x_ref = _reference(3000, design.period_s)
    x_ref[1000:, 0] += 0.5  # a step that saturates at 0.7 A
    expected = _closed_loop(design, x_ref, limit)
    for dob in (True, False):  # no disturbance: the DOB's output stays zero
        y = nominal_output(
            design, x_ref, dob_enabled=dob, current_limit_A=None if limit == math.inf else limit
        )
        np.testing.assert_allclose(y, expected, rtol=1e-9, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 30000),
    max_points=st.integers(4, 2000),
    seed=st.integers(0, 2**32 - 1),
    nan_fraction=st.sampled_from([0.0, 0.1]),
)
def test_envelope_keeps_every_bucket_extreme(n: int, max_points: int, seed: int, nan_fraction: float) -> None:
    rng = np.random.default_rng(seed)
    y = np.cumsum(rng.standard_normal(n))
    y[rng.random(n) < nan_fraction] = np.nan
    idx = envelope_indices(y, max_points)
    assert np.all(np.diff(idx) > 0) and idx[-1] == n - 1
    assert len(idx) <= (n if n <= max_points else max_points + 1)
    kept = y[idx]
    if np.isfinite(y).any():
        assert np.nanmax(kept) == np.nanmax(y) and np.nanmin(kept) == np.nanmin(y)


def _exact_quantize(u: float, lsb: float, limit: float) -> tuple[int, bool]:
    """clamp(round half away from zero(u / lsb), -L, L), L = floor(limit / lsb), in exact arithmetic."""
    L = math.floor(Fraction(limit) / Fraction(lsb))
    q = Fraction(u) / Fraction(lsb)
    code = math.floor(abs(q) + Fraction(1, 2)) * (1 if q >= 0 else -1)
    return max(-L, min(L, code)), abs(code) > L


@settings(max_examples=300, deadline=None)
@given(
    u=st.floats(-5.0, 5.0),
    lsb=st.sampled_from([1.0 / 2048.0, 0.01, 1e-3, 0.0007]),
    limit=st.sampled_from([0.7, 1.0, 2.5]),
)
def test_dac_quantizer_is_exact_and_the_link_delegates_to_it(u: float, lsb: float, limit: float) -> None:
    drive = DriveConfig(current_limit_A=limit, dac_lsb_A=lsb)
    q = DacQuantizer(drive)
    (code,), (applied,), saturated = q.quantize((u,))
    assert (code, saturated) == _exact_quantize(u, lsb, limit)
    assert applied == code * lsb and abs(applied) <= limit
    with can.Bus(interface="virtual", channel="dob-hil-quantizer-test") as bus:
        link = NativeDriveLink(bus, drive)
        assert link.quantize((u,)) == q.quantize((u,))
        assert link.limit_code == q.limit_code and link.max_current_A == q.max_current_A


def test_dac_quantizer_refuses_non_finite_currents_and_bad_settings() -> None:
    q = DacQuantizer(DriveConfig())
    assert q.quantize((math.nan,)) == ((0,), (0.0,), True)
    assert q.quantize((math.inf,)) == ((0,), (0.0,), True)
    from dob_hil.errors import ConfigError

    with pytest.raises(ConfigError, match=r"drive\.dac_lsb_A"):
        DacQuantizer(DriveConfig(dac_lsb_A=0.0))
    with pytest.raises(ConfigError, match=r"drive\.current_limit_A"):
        DacQuantizer(DriveConfig(current_limit_A=1e-6))
