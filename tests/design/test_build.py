"""build_design end to end: the paper's printed numbers, a MIMO plant, an input delay, refusals."""

from __future__ import annotations

import math

import control
import numpy as np
import pytest
import scipy.optimize

from dob_hil.config import Config
from dob_hil.design import build_design, design_with_diagnostics
from dob_hil.design.discretize import zoh
from dob_hil.design.theorem1 import dob_matrix, estimator_matrix, feedback_matrix
from dob_hil.errors import DesignError

from .conftest import MIMO_PLANT, PAPER_PLANT, make_config


def _agrees_to_significant_digits(value: float, printed: float, digits: int) -> bool:
    """|value - printed| within half a unit in the last of ``digits`` significant digits of ``printed``."""
    unit = 10.0 ** (math.floor(math.log10(abs(printed))) - (digits - 1))
    return abs(value - printed) <= 0.5 * unit


def test_paper_example_reproduces_the_printed_phi_and_gam(paper_config: Config) -> None:
    d = build_design(paper_config)
    printed_phi = [[1.0, 2.9429e-4], [0.0, 9.6216e-1]]
    printed_gam = [9.5445e-4, 6.3224]
    for i in range(2):
        for j in range(2):
            if printed_phi[i][j] == 0.0:
                assert d.Phi[i, j] == 0.0
            else:
                assert _agrees_to_significant_digits(float(d.Phi[i, j]), printed_phi[i][j], 4)
                assert _agrees_to_significant_digits(float(d.Phi[i, j]), printed_phi[i][j], 5)
        assert _agrees_to_significant_digits(float(d.Gam[i, 0]), printed_gam[i], 4)
    # Honest detail: to the five digits the paper prints, Gam is 9.5447e-4 and 6.3225 (the paper's
    # 9.5445e-4 and 6.3224 are 1.7 and 0.65 units off in the fifth digit).
    assert f"{d.Gam[0, 0]:.4e}" == "9.5447e-04"
    assert f"{d.Gam[1, 0]:.4e}" == "6.3225e+00"


def test_paper_example_reproduces_the_printed_spectral_radii(paper_config: Config) -> None:
    radii = build_design(paper_config).spectral_radii
    assert [round(v, 2) for v in radii["estimator"]] == [0.25, 0.96]
    assert [round(v, 3) for v in radii["feedback"]] == [0.895, 0.932]
    assert [round(v, 2) for v in radii["feedback"]] == [0.89, 0.93]  # the paper prints 0.895, 0.93
    assert [round(v, 2) for v in radii["dob"]] == [0.28, 0.92]


def test_paper_kc_is_not_on_the_ltr_dare_family(paper_config: Config) -> None:
    """For a SISO plant Kc(q, R2) depends on q / R2 only: one curve. Where its position gain equals the
    paper's 107.42, its velocity gain is far from the paper's 0.3 -- the paper's Kc was tuned by hand."""
    d = build_design(paper_config)

    def kc(log_q: float) -> np.ndarray:
        return np.asarray(control.dare(d.Phi, d.Gam, 10.0**log_q * d.C.T @ d.C, np.eye(1))[2])

    log_q = scipy.optimize.brentq(lambda x: kc(x)[0, 0] - 107.42, 0.0, 8.0)
    K = kc(log_q)
    assert K[0, 0] == pytest.approx(107.42, rel=1e-9)
    assert K[0, 1] < 0.5 * 0.3


def test_mimo_plant_designed_end_to_end(mimo_config: Config) -> None:
    r = design_with_diagnostics(mimo_config)
    d = r.design
    assert (d.n_states, d.n_inputs, d.n_outputs) == (4, 2, 2)
    assert r.estimator_dare is not None and r.feedback_dare is not None
    assert r.estimator_dare.relative_residual < 1e-10
    assert r.feedback_dare.relative_residual < 1e-10
    # Independent solutions of both DAREs with the configured weights.
    Gam1 = mimo_config.design.estimator.Gam1
    D1 = mimo_config.design.estimator.D1
    R2 = mimo_config.design.feedback.R2
    assert Gam1 is not None and D1 is not None and R2 is not None
    R1 = 1.0e4 * d.C.T @ d.C
    _, _, K_ct = control.dare(d.Phi, d.Gam, 0.5 * (R1 + R1.T), R2)
    np.testing.assert_allclose(d.Kc, K_ct, rtol=1e-7)
    Y_ct, _, _ = control.dare(d.Phi.T, d.C.T, Gam1 @ Gam1.T, D1 @ D1.T)
    np.testing.assert_allclose(d.Lc, Y_ct @ d.C.T @ np.linalg.inv(d.C @ Y_ct @ d.C.T + D1 @ D1.T), rtol=1e-7)
    for key in ("estimator", "feedback", "dob"):
        assert max(d.spectral_radii[key]) < 1.0
    assert "q = 10000" in d.gain_sources["Kc"] and "R2 = given" in d.gain_sources["Kc"]
    assert "Gam1 = given" in d.gain_sources["Lc"] and "D1 = given" in d.gain_sources["Lc"]


def test_default_weights_are_gam_w_identity_and_q_one() -> None:
    r = design_with_diagnostics(make_config(PAPER_PLANT))
    assert r.q == 1.0
    np.testing.assert_array_equal(r.R2, np.eye(1))
    assert r.Gam1 is not None and r.D1 is not None
    np.testing.assert_array_equal(r.Gam1, r.design.Gam_w)
    np.testing.assert_array_equal(r.D1, np.eye(1))
    assert "(default)" in r.design.gain_sources["Lc"] and "(default)" in r.design.gain_sources["Kc"]


def test_input_delay_plant_is_designed_on_the_augmented_model(delay_config: Config) -> None:
    d = build_design(delay_config)
    n, delay, m = 2, 2, 1
    N = n + delay * m
    assert d.n_plant_states == n and d.input_delay_samples == delay
    assert d.Phi.shape == (N, N) and d.Gam.shape == (N, m) and d.C.shape == (1, N)
    assert d.Lc.shape == (N, 1) and d.Kc.shape == (1, N) and d.Kdist.shape == (1, N)
    assert d.state_names == ("x1", "x2", "u1(k-2)", "u1(k-1)")
    Phi0, Gam0 = zoh(d.A, d.B, d.period_ns)
    np.testing.assert_array_equal(d.Phi[:n, :n], Phi0)
    np.testing.assert_array_equal(d.Phi[:n, n : n + m], Gam0)
    np.testing.assert_array_equal(d.Gam[-m:], np.eye(m))
    # Theorem-1 eigenvalue magnitudes are those of the augmented matrices, all inside the unit circle.
    for key, M in (
        ("estimator", estimator_matrix(d.Phi, d.C, d.Lc)),
        ("feedback", feedback_matrix(d.Phi, d.Gam, d.Kc)),
        ("dob", dob_matrix(d.Phi, d.Gam, d.C, d.Lc, d.Kdist)),
    ):
        np.testing.assert_allclose(d.spectral_radii[key], sorted(abs(np.linalg.eigvals(M))), atol=1e-12)
        assert len(d.spectral_radii[key]) == N and max(d.spectral_radii[key]) < 1.0


def _paper_with_kdist(kdist: str, run: str = "") -> Config:
    return make_config(
        PAPER_PLANT,
        f"""
[design.estimator]
Lc = [0.75, 0.5]
[design.feedback]
Kc = [[107.42, 0.3]]
[design.dob]
Kdist = {kdist}
""",
        run,
    )


def test_huge_kdist_is_refused_naming_the_dob_matrix_and_its_radius() -> None:
    with pytest.raises(
        DesignError, match=r"^dob: rho\(Phi - Phi Lc C - Gam Kdist Lc C\) = (\d+\.\d+) >= 1"
    ) as info:
        build_design(_paper_with_kdist("[[1800.0, 375.0]]"))
    assert "stable DOB gains along pinv(H(1)): 0 <= k < 53.59" in str(info.value)


def test_disabled_dob_does_not_require_a_stable_dob_matrix_but_reports_it() -> None:
    cfg = _paper_with_kdist("[[1800.0, 375.0]]", "[run]\ndob_enabled = false\n")
    d = build_design(cfg)
    assert max(d.spectral_radii["dob"]) > 1.0
    with pytest.raises(DesignError, match=r"^dob: "):
        d.require_stable(dob_enabled=True)
    with pytest.raises(DesignError, match=r"^dob: "):
        build_design(cfg, dob_enabled=True)  # --dob overrides the config


def test_unstable_feedback_and_estimator_are_refused() -> None:
    cfg = make_config(
        PAPER_PLANT,
        """
[design.estimator]
Lc = [0.75, 0.5]
[design.feedback]
Kc = [[-10.0, 0.3]]
""",
    )
    with pytest.raises(DesignError, match=r"^feedback: rho\(Phi - Gam Kc\) = \d"):
        build_design(cfg)
    cfg = make_config(PAPER_PLANT, "[design.estimator]\nLc = [3.0, 0.0]\n")
    with pytest.raises(DesignError, match=r"^estimator: rho\(Phi - Phi Lc C\) = \d"):
        build_design(cfg)


def test_estimator_weights_with_wrong_shapes_are_refused() -> None:
    cfg = make_config(MIMO_PLANT, "[design.estimator]\nD1 = [[1.0, 0.0], [0.0, 0.0]]\n")
    with pytest.raises(DesignError, match="D1 D1': must be positive definite"):
        build_design(cfg)
