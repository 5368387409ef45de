"""The figures of merit of issue 15 against independent computations (python-control interconnections
of the run-time equations, python-control's disk_margins and norm), and the Theorem-1 gate."""

from __future__ import annotations

import math
import warnings

import control
import numpy as np
import pytest

from dob_hil.config import Config
from dob_hil.design import Design, build_design, design_with_diagnostics
from dob_hil.design.analysis import analyze
from dob_hil.design.dob import disturbance_estimate_response
from dob_hil.design.linalg import max_singular_value, unit_circle_points
from dob_hil.design.loops import loop_response
from dob_hil.design.robustness import (
    DesignWarning,
    analysis_grid_rad_s,
    classical_margins,
    damping_ratio,
    disk_margin,
    evaluate,
    noise_rms,
    pole_flags,
)
from dob_hil.design.theorem1 import feedback_matrix
from dob_hil.errors import DesignError

from .conftest import PAPER_PLANT, make_config
from .helpers import block, runtime_interconnection, sub_system

COUNT = 1e-4  # one encoder count of the paper's drive (10000 counts per rev)


def _quiet_design(cfg: Config) -> Design:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DesignWarning)
        return build_design(cfg)


@pytest.mark.parametrize("name", ["paper", "delay", "mimo"])
@pytest.mark.parametrize("dob", [True, False])
def test_Q_is_the_interconnections_disturbance_to_estimate(
    designs: dict[str, Design], name: str, dob: bool
) -> None:
    d = designs[name]
    Kd = d.Kdist if dob else np.zeros_like(d.Kdist)
    w = np.array([0.5, 10.0, 300.0, 0.9 * math.pi / d.period_s])
    Q = disturbance_estimate_response(d.Phi, d.Gam, d.Gam_w, d.C, d.Lc, Kd, unit_circle_points(w, d.period_s))
    cl = runtime_interconnection(d, dob)
    G = sub_system(cl, "ud", "w").frequency_response(w).fresp
    ref = -np.moveaxis(G, -1, 0)  # the estimate is -u_dist
    np.testing.assert_allclose(Q, ref, rtol=1e-7, atol=1e-12)


def test_Q_of_the_papers_gains_estimates_half_a_constant_disturbance(designs: dict[str, Design]) -> None:
    d = designs["paper"]
    Q1 = disturbance_estimate_response(d.Phi, d.Gam, d.Gam_w, d.C, d.Lc, d.Kdist, np.array([1.0 + 0j]))
    assert Q1[0, 0, 0].real == pytest.approx(0.5055, abs=5e-5)


@pytest.mark.parametrize("name", ["paper", "delay", "mimo"])
def test_noise_to_current_matches_python_control(designs: dict[str, Design], name: str) -> None:
    d = designs[name]
    cl = runtime_interconnection(d, True)
    n_to_u = sub_system(cl, "u", "d")  # d: added to the measured output, i.e. encoder noise
    rms = noise_rms(d.Phi, d.Gam, d.C, Lc=d.Lc, Kc=d.Kc, Kdist=d.Kdist, count=COUNT)
    # H2 as the impulse response's energy (python-control's norm() returns inf for the delay model,
    # whose nilpotent delay modes make its Gramian test fail; where it is finite it agrees)
    T = np.arange(6000) * d.period_s
    for i in range(d.n_inputs):
        # python-control's discrete impulse has area one (height 1/dt): scale back to a unit pulse
        h = np.asarray(control.impulse_response(n_to_u[i, :], T=T).outputs) * d.period_s
        h2 = math.sqrt(float(np.sum(h**2)))
        assert rms[i] == pytest.approx(h2 * COUNT, rel=1e-6)
        h2_norm = float(control.norm(n_to_u[i, :], p=2, print_warning=False))
        if math.isfinite(h2_norm):
            assert rms[i] == pytest.approx(h2_norm * COUNT, rel=1e-6)
    w = analysis_grid_rad_s(d.period_s)
    G = block(cl.frequency_response(w).fresp, cl, "u", "d")
    merit = evaluate(d.Phi, d.Gam, d.Gam_w, d.C, Lc=d.Lc, Kc=d.Kc, Kdist=d.Kdist, period_s=d.period_s,
                     omega_rad_s=w, band_hz=np.array([4.0]), count=COUNT)  # fmt: skip
    assert merit.noise_peak_A == pytest.approx(float(np.max(max_singular_value(G))) * COUNT, rel=1e-7)


def test_papers_noise_to_current_figures(designs: dict[str, Design]) -> None:
    """Issue 15: 0.197 A for one count alternating at Nyquist with the paper's Kc."""
    d = designs["paper"]
    r = loop_response(d.Phi, d.Gam, d.Gam_w, d.C, Lc=d.Lc, Kc=d.Kc, Kdist=d.Kdist, period_s=d.period_s,
                      omega_rad_s=np.array([math.pi / d.period_s]))  # fmt: skip
    assert abs(r.K[0, 0, 0]) * COUNT == pytest.approx(0.197, abs=1e-3)
    rms = noise_rms(d.Phi, d.Gam, d.C, Lc=d.Lc, Kc=d.Kc, Kdist=d.Kdist, count=COUNT)
    assert rms[0] == pytest.approx(0.0372, abs=1e-4)


@pytest.mark.parametrize("name", ["paper", "delay"])
@pytest.mark.parametrize("dob", [True, False])
def test_balanced_disk_margins_match_python_control(designs: dict[str, Design], name: str, dob: bool) -> None:
    d = designs[name]
    cl = runtime_interconnection(d, dob, open_at_plant_input=True)
    L = -sub_system(cl, "u", "uin")  # the loop broken at the plant input, negative feedback
    w = analysis_grid_rad_s(d.period_s, 3000)
    dm_ref, dgm_ref, dpm_ref = control.disk_margins(L, w, skew=0.0)
    Kd = d.Kdist if dob else np.zeros_like(d.Kdist)
    r = loop_response(
        d.Phi, d.Gam, d.Gam_w, d.C, Lc=d.Lc, Kc=d.Kc, Kdist=Kd, period_s=d.period_s, omega_rad_s=w
    )
    dm = disk_margin(r.Si[:, 0, 0], w)
    assert dm.alpha == pytest.approx(float(dm_ref), rel=1e-6)
    assert dm.gain_margin_db == pytest.approx(float(dgm_ref), rel=1e-6)
    assert dm.phase_margin_deg == pytest.approx(float(dpm_ref), rel=1e-6)


def test_papers_disk_margins_are_the_issues_figures(designs: dict[str, Design]) -> None:
    d = designs["paper"]
    w = analysis_grid_rad_s(d.period_s, 3000)
    r = loop_response(d.Phi, d.Gam, d.Gam_w, d.C, Lc=d.Lc, Kc=d.Kc, Kdist=d.Kdist, period_s=d.period_s,
                      omega_rad_s=w)  # fmt: skip
    dm = disk_margin(r.S[:, 0, 0], w)
    assert round(dm.gain_margin_db, 1) == 17.7 and round(dm.phase_margin_deg, 1) == 75.2
    # S + T = I, so alpha = 2 / max |S - T|
    T = 1.0 - r.S[:, 0, 0]
    assert dm.alpha == pytest.approx(2.0 / float(np.max(np.abs(r.S[:, 0, 0] - T))), rel=1e-12)


def test_delay_margin_is_the_delay_that_destabilises(designs: dict[str, Design]) -> None:
    """A pure delay tau = the margin puts the loop's Nyquist curve through -1 at the crossover."""
    d = designs["paper"]
    w = analysis_grid_rad_s(d.period_s, 20000)
    r = loop_response(d.Phi, d.Gam, d.Gam_w, d.C, Lc=d.Lc, Kc=d.Kc, Kdist=d.Kdist, period_s=d.period_s,
                      omega_rad_s=w)  # fmt: skip
    loop = 1.0 / r.Si[:, 0, 0] - 1.0
    _, pm, tau = classical_margins(loop, w)
    delayed = loop * np.exp(-1j * w * tau)
    assert float(np.min(np.abs(1.0 + delayed))) < 2e-3
    assert tau == pytest.approx(math.radians(pm) / w[np.argmin(np.abs(np.abs(loop) - 1.0))], rel=1e-3)


def test_pole_flags_find_the_papers_chatter_pole(designs: dict[str, Design]) -> None:
    d = designs["paper"]
    flags = pole_flags({"feedback": feedback_matrix(d.Phi, d.Gam, d.Kc)})
    assert [f.kind for f in flags] == ["negative real"]
    assert flags[0].real == pytest.approx(-0.9316, abs=1e-4)
    assert damping_ratio(complex(0.5, 0.0)) == pytest.approx(1.0)
    z = np.exp(complex(-0.01, 1.0))  # zeta = 0.01 / sqrt(1.0001)
    assert damping_ratio(z) == pytest.approx(0.01 / math.sqrt(1.0001), rel=1e-9)
    light = pole_flags({"m": np.array([[z.real, -z.imag], [z.imag, z.real]])})
    assert [f.kind for f in light] == ["lightly damped"]


def test_theorem1_gate_accepts_an_unstable_estimator_when_the_loop_with_the_dob_is_stable(
    designs: dict[str, Design],
) -> None:
    """The DOB matrix is Phi - (Phi Lc + k Gam) C with k = Kdist Lc: keep the paper's stable
    Phi Lc + k Gam but move k to 60, which makes Phi - Phi Lc C alone unstable."""
    p = designs["paper"]
    k = 60.0
    Lc = np.linalg.solve(p.Phi, p.Phi @ p.Lc - k * p.Gam)
    Kdist = k * np.linalg.pinv(Lc)
    design = (
        f"[design.estimator]\nLc = [{float(Lc[0, 0])!r}, {float(Lc[1, 0])!r}]\n"
        "[design.feedback]\nKc = [[107.42, 0.3]]\n"
        f"[design.dob]\nKdist = [[{float(Kdist[0, 0])!r}, {float(Kdist[0, 1])!r}]]\n"
    )
    cfg = make_config(PAPER_PLANT, design)
    d = _quiet_design(cfg)
    assert max(d.spectral_radii["estimator"]) > 1.05
    assert max(d.spectral_radii["dob"]) < 1.0 and max(d.spectral_radii["feedback"]) < 1.0
    # Theorem 1's union: the closed loop's eigenvalues are the feedback's and the DOB matrix's
    cl = runtime_interconnection(d, True)
    expected = np.concatenate([np.linalg.eigvals(p.Phi - p.Gam @ d.Kc), np.linalg.eigvals(
        d.Phi - d.Phi @ d.Lc @ d.C - d.Gam @ d.Kdist @ d.Lc @ d.C)])  # fmt: skip
    poles = cl.poles()
    for ev in expected:
        assert float(np.min(np.abs(poles - ev))) < 1e-6
    # the same design must not run without the DOB (the estimator's modes are then closed-loop modes)
    with pytest.raises(DesignError, match=r"estimator: rho"):
        build_design(cfg, dob_enabled=False)


def test_design_warns_when_the_dob_cuts_the_delay_margin_below_one_sample(delay_config: Config) -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DesignWarning)
        r = design_with_diagnostics(delay_config)
    msgs = [str(c.message) for c in caught if issubclass(c.category, DesignWarning)]
    assert any("delay margin" in m and "< 1 sample" in m for m in msgs)
    assert set(msgs) == set(r.warnings)
    report = analyze(r, delay_config).to_dict()
    assert report["warnings"] == list(r.warnings)
    assert report["loop_dob_on"]["delay_margin"]["samples"] < 1.0
