"""The DOB gain design methods and the locus that shows the trade-off."""

from __future__ import annotations

import numpy as np
import pytest

from dob_hil.config import Config
from dob_hil.design import build_design, design_with_diagnostics
from dob_hil.design.dob import design_dob, locus_radius
from dob_hil.design.linalg import spectral_radius
from dob_hil.design.theorem1 import dob_matrix, estimator_matrix
from dob_hil.errors import ConfigError, DesignError

from .conftest import MIMO_PLANT, PAPER_PLANT, make_config

PAPER_GAINS = """
[design.estimator]
Lc = [0.75, 0.5]
[design.feedback]
Kc = [[107.42, 0.3]]
"""


def _paper_with_dob(dob: str) -> Config:
    return make_config(PAPER_PLANT, PAPER_GAINS + "[design.dob]\n" + dob)


def test_the_papers_kdist_is_a_dob_loop_dc_gain_of_about_one(paper_config: Config) -> None:
    r = design_with_diagnostics(paper_config)
    assert r.dob.method == "explicit"
    assert r.dob.direction_kind == "pinv(H(1))"
    assert r.dob.gain == pytest.approx(1.0222, abs=1e-4)
    np.testing.assert_allclose(r.dob.Kdist_Lc, [[15.375]], rtol=1e-15)
    np.testing.assert_allclose(r.dob.dc_loop_gain, r.dob.Kdist_Lc @ r.dob.H1, rtol=1e-15)
    # The design point lies on its own locus, inside the stable range.
    d = r.design
    A0 = estimator_matrix(d.Phi, d.C, d.Lc)
    rho = locus_radius(A0, d.Gam, d.C, r.dob.direction, np.array([r.dob.gain]))[0]
    assert rho == pytest.approx(max(d.spectral_radii["dob"]), rel=1e-12)
    assert r.dob.k_max is not None and r.dob.gain < r.dob.k_max


def test_dc_loop_gain_method_sets_the_dob_loop_dc_gain() -> None:
    d = build_design(_paper_with_dob('method = "dc_loop_gain"\ngain = 2.5\n'))
    r = design_with_diagnostics(_paper_with_dob('method = "dc_loop_gain"\ngain = 2.5\n'))
    np.testing.assert_allclose(r.dob.dc_loop_gain, [[2.5]], rtol=1e-12)
    np.testing.assert_allclose(d.Kdist @ d.Lc, r.dob.Kdist_Lc, rtol=1e-14)
    # Minimum-norm Kdist: its rows lie in the range of Lc'.
    np.testing.assert_allclose(d.Kdist, (d.Kdist @ d.Lc) @ np.linalg.pinv(d.Lc), rtol=1e-14)


def test_dc_loop_gain_is_the_default_method_with_gain_one() -> None:
    r = design_with_diagnostics(make_config(PAPER_PLANT, PAPER_GAINS))
    assert r.dob.method == "dc_loop_gain" and r.dob.gain == 1.0
    np.testing.assert_allclose(r.dob.dc_loop_gain, [[1.0]], rtol=1e-12)


def test_stable_fraction_places_the_gain_at_a_fraction_of_the_stability_edge() -> None:
    r = design_with_diagnostics(_paper_with_dob('method = "stable_fraction"\ngain = 0.25\n'))
    d = r.design
    assert r.dob.k_max is not None
    assert r.dob.gain == pytest.approx(0.25 * r.dob.k_max, rel=1e-12)
    A0 = estimator_matrix(d.Phi, d.C, d.Lc)
    edge = locus_radius(A0, d.Gam, d.C, r.dob.direction, np.array([r.dob.k_max, 0.999 * r.dob.k_max]))
    assert edge[0] == pytest.approx(1.0, abs=1e-9)
    assert edge[1] < 1.0
    with pytest.raises(ConfigError, match=r"design\.dob\.gain: stable_fraction needs 0 < gain < 1"):
        build_design(_paper_with_dob('method = "stable_fraction"\ngain = 1.5\n'))


def test_min_radius_is_a_local_minimum_of_the_locus() -> None:
    r = design_with_diagnostics(_paper_with_dob('method = "min_radius"\n'))
    d = r.design
    A0 = estimator_matrix(d.Phi, d.C, d.Lc)
    rho = spectral_radius(dob_matrix(d.Phi, d.Gam, d.C, d.Lc, d.Kdist))
    assert rho == pytest.approx(r.dob.min_radius, rel=1e-9)
    # over the gains that estimate at least half of a constant disturbance (the default floor)
    assert r.dob.dc_estimate_gain[0, 0] >= 0.5 - 1e-9
    grid = np.linspace(1.0, r.dob.k_max or 10.0, 2001)  # no delay: Q(1) = k / (1 + k) >= 0.5
    assert rho <= locus_radius(A0, d.Gam, d.C, r.dob.direction, grid).min() + 1e-6
    assert rho < max(d.spectral_radii["estimator"])  # the DOB made the estimate faster
    with pytest.raises(ConfigError, match=r"design\.dob\.gain: min_radius needs 0 < gain < 1"):
        build_design(_paper_with_dob('method = "min_radius"\ngain = 1.0\n'))


def test_unknown_method_names_the_field() -> None:
    with pytest.raises(ConfigError, match=r"design\.dob\.method: must be one of dc_loop_gain"):
        build_design(_paper_with_dob('method = "pole_placement"\n'))


def test_mimo_dob_direction_decouples_the_dc_loop_gain(mimo_config: Config) -> None:
    r = design_with_diagnostics(mimo_config)
    np.testing.assert_allclose(r.dob.dc_loop_gain, 0.5 * np.eye(2), atol=1e-12)
    # Q(1) = G (I + G)^-1 = 1/3 I when there is no delay.
    np.testing.assert_allclose(r.dob.dc_estimate_gain, np.eye(2) / 3.0, atol=1e-10)


def test_explicit_kdist_not_along_the_dc_direction_uses_its_own_scale() -> None:
    cfg = make_config(
        MIMO_PLANT,
        """
[design.dob]
Kdist = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]
""",
    )
    r = design_with_diagnostics(cfg)
    assert r.dob.direction_kind == "Kdist Lc" and r.dob.gain == 1.0
    np.testing.assert_allclose(r.dob.direction, r.design.Kdist_Lc)


def test_design_dob_refuses_an_unstable_estimator() -> None:
    Phi, Gam, C = np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.0], [0.1]]), np.array([[1.0, 0.0]])
    with pytest.raises(DesignError, match=r"estimator: rho\(Phi - Phi Lc C\)"):
        design_dob(Phi, Gam, Gam, C, np.array([[3.0], [0.0]]), Kdist=None, method=None, gain=None)
