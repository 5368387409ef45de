"""The optimize method (issue 15): every bound holds at the result, and from the paper's gains it finds
the 3x rejection of paper-step-optimized; the Kdist methods never return a zero or silent gain."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from dob_hil.config import Config, load_config, parse_config_text
from dob_hil.design import design_with_diagnostics
from dob_hil.design.build import DesignResult
from dob_hil.design.dob import DOB_METHODS, MIN_DC_ESTIMATE
from dob_hil.design.linalg import max_singular_value
from dob_hil.design.loops import loop_response
from dob_hil.design.optimize import band_frequencies
from dob_hil.design.robustness import DesignWarning, analysis_grid_rad_s, noise_rms
from dob_hil.errors import DesignError
from dob_hil.scenarios import scenario_names, scenario_path

from .conftest import DELAY_DESIGN, MIMO_DESIGN, MIMO_PLANT, PAPER_PLANT, make_config

PAPER_GAINS = {"Lc": "[0.75, 0.5]", "Kc": "[[107.42, 0.3]]", "Kdist": "[[18.0, 3.75]]"}


def _optimized_scenario_from_the_papers_gains() -> Config:
    """paper-step-optimized with its gains replaced by the paper's: the search its comment describes."""
    text = scenario_path("paper-step-optimized").read_text()
    cfg = load_config(scenario_path("paper-step-optimized"))
    for key, value in (
        ("Lc", cfg.design.estimator.Lc),
        ("Kc", cfg.design.feedback.Kc),
        ("Kdist", cfg.design.dob.Kdist),
    ):
        assert value is not None
        line = next(ln for ln in text.splitlines() if ln.startswith(f"{key} = "))
        text = text.replace(line, f"{key} = {PAPER_GAINS[key]}")
    return parse_config_text(text)


def _quiet(cfg: Config, **kw: bool) -> DesignResult:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DesignWarning)
        return design_with_diagnostics(cfg, **kw)


@pytest.fixture(scope="module")
def optimized() -> DesignResult:
    return _quiet(_optimized_scenario_from_the_papers_gains(), optimize=True)


def test_optimize_from_the_papers_gains_rejects_3x_better_within_the_bounds(optimized: DesignResult) -> None:
    o = optimized.optimized
    assert o is not None and o.improved and o.tune == "all"
    assert o.start.rejection[0] == pytest.approx(0.2408, abs=1e-4)  # the paper's |y/w| at 4 Hz
    assert o.rejection_gain >= 3.0
    assert np.all(o.start.rejection / o.merit.rejection >= 3.0)  # at every band frequency, 4 ... 12 Hz
    b = o.bounds
    assert b.max_peak_S == 1.6 and b.max_peak_T == 1.0307 and b.max_noise_rms_A == 0.0372


def test_optimize_result_satisfies_every_bound_by_an_independent_check(optimized: DesignResult) -> None:
    """Recompute the figures on a much finer grid with the loop algebra, not the optimiser's grid."""
    o = optimized.optimized
    assert o is not None
    d = optimized.design
    w = analysis_grid_rad_s(d.period_s, 8000)
    r = loop_response(d.Phi, d.Gam, d.Gam_w, d.C, Lc=d.Lc, Kc=d.Kc, Kdist=d.Kdist, period_s=d.period_s,
                      omega_rad_s=w)  # fmt: skip
    tol = 1e-3  # the optimiser's grid is coarser; peaks between its points may be a little higher
    assert float(np.max(max_singular_value(r.S))) <= o.bounds.max_peak_S * (1 + tol)
    assert float(np.max(max_singular_value(r.T))) <= o.bounds.max_peak_T * (1 + tol)
    rms = noise_rms(d.Phi, d.Gam, d.C, Lc=d.Lc, Kc=d.Kc, Kdist=d.Kdist, count=1e-4)
    assert float(rms[0]) <= o.bounds.max_noise_rms_A * (1 + 1e-9)
    assert max(d.spectral_radii["feedback"] + d.spectral_radii["dob"]) < 0.999
    m = o.merit
    assert abs(m.gain_margin_db) >= o.bounds.min_gain_margin_dB
    assert m.phase_margin_deg >= o.bounds.min_phase_margin_deg
    assert m.delay_margin_s / d.period_s >= o.bounds.min_delay_margin_samples
    # the rejection figure itself, from the loop algebra at the band frequencies
    fb = band_frequencies(o.band_hz)
    rb = loop_response(d.Phi, d.Gam, d.Gam_w, d.C, Lc=d.Lc, Kc=d.Kc, Kdist=d.Kdist, period_s=d.period_s,
                       omega_rad_s=2 * math.pi * fb)  # fmt: skip
    np.testing.assert_allclose(max_singular_value(rb.disturbance), m.rejection, rtol=1e-12)


def test_shipped_optimized_gains_are_what_the_search_finds(optimized: DesignResult) -> None:
    shipped = load_config(scenario_path("paper-step-optimized"))
    o = optimized.optimized
    assert (
        o is not None and shipped.design.estimator.Lc is not None and shipped.design.feedback.Kc is not None
    )
    np.testing.assert_allclose(o.Lc, shipped.design.estimator.Lc, rtol=2e-3)
    np.testing.assert_allclose(o.Kc, shipped.design.feedback.Kc, rtol=2e-3, atol=1e-3)


def test_shipped_optimized_design_beats_the_paper_3x_at_equal_or_lower_T_and_noise() -> None:
    paper = _quiet(load_config(scenario_path("paper-step")))
    opt = _quiet(load_config(scenario_path("paper-step-optimized")))
    w_band = 2 * math.pi * np.array([4.0, 12.0])
    w = analysis_grid_rad_s(300e-6, 8000)
    figures = {}
    for name, r in (("paper", paper), ("optimized", opt)):
        d = r.design
        rb = loop_response(d.Phi, d.Gam, d.Gam_w, d.C, Lc=d.Lc, Kc=d.Kc, Kdist=d.Kdist, period_s=d.period_s,
                           omega_rad_s=w_band)  # fmt: skip
        rg = loop_response(d.Phi, d.Gam, d.Gam_w, d.C, Lc=d.Lc, Kc=d.Kc, Kdist=d.Kdist, period_s=d.period_s,
                           omega_rad_s=w)  # fmt: skip
        figures[name] = (
            max_singular_value(rb.disturbance),
            float(np.max(max_singular_value(rg.T))),
            float(noise_rms(d.Phi, d.Gam, d.C, Lc=d.Lc, Kc=d.Kc, Kdist=d.Kdist, count=1e-4)[0]),
        )
    (rej_p, T_p, n_p), (rej_o, T_o, n_o) = figures["paper"], figures["optimized"]
    assert np.all(rej_p / rej_o >= 3.0)
    assert T_o <= T_p and n_o <= n_p


def test_optimize_kdist_only_never_loses_and_meets_the_bounds(paper_config: Config) -> None:
    text = scenario_path("paper-sine").read_text() + "\n[design.optimize]\nmax_peak_S = 1.3\n"
    r = _quiet(parse_config_text(text), optimize=True)
    o = r.optimized
    assert o is not None and o.tune == "kdist" and o.band_hz == (4.0, 12.0)  # from the disturbances
    np.testing.assert_array_equal(o.Lc, r.design.Lc)
    assert o.merit.worst_rejection <= o.start.worst_rejection
    assert o.merit.peak_S <= 1.3 + 1e-9 and o.merit.peak_T <= o.start.peak_T * (1 + 1e-9)
    assert float(np.max(o.merit.noise_rms_A)) <= float(np.max(o.start.noise_rms_A)) * (1 + 1e-9)


def test_optimize_method_key_and_unmeetable_bounds() -> None:
    opt = '[design.dob]\nmethod = "optimize"\n[design.optimize]\nband_hz = [4.0, 12.0]\n'
    r = _quiet(make_config(PAPER_PLANT, opt))
    assert r.dob.method == "optimize" and r.optimized is not None and np.any(r.design.Kdist)
    bad = make_config(PAPER_PLANT, opt + "max_peak_T = 0.9\n")  # |T(1)| = 1 for this plant
    with pytest.raises(DesignError, match=r"design\.optimize: no design meets the bounds"):
        _quiet(bad)


def test_design_command_optimize_writes_the_tradeoff(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from dob_hil.commands.design import write_design_outputs

    cfg = make_config(PAPER_PLANT, "[design.optimize]\nband_hz = [4.0, 12.0]\n")
    report = write_design_outputs(cfg, tmp_path, optimize=True)
    assert (tmp_path / "tradeoff.png").is_file() and (tmp_path / "dob_filter.png").is_file()
    assert report["optimize"]["result"]["worst_rejection"] <= report["optimize"]["start"]["worst_rejection"]
    out = capsys.readouterr().out
    assert "optimize (tune kdist" in out and "[design.dob]\nKdist = [[" in out
    json.dumps(report, allow_nan=False)


# ---- the Kdist design methods, across plants ------------------------------------------------------

PLANTS = {
    "paper-dare": (PAPER_PLANT, ""),
    "one-sample-delay": (PAPER_PLANT + "input_delay_samples = 1\n", ""),
    "delay": (PAPER_PLANT + "input_delay_samples = 2\n", DELAY_DESIGN.split("[design.dob]")[0]),
    "2x2": (MIMO_PLANT, MIMO_DESIGN.split("[design.dob]")[0]),
    **{name: ("", "") for name in scenario_names()},
}


def _plant_config(name: str, dob: str) -> Config:
    if name in scenario_names():
        text = scenario_path(name).read_text()
        start = text.index("[design.dob]")
        end = text.index("\n[", start + 1)
        return parse_config_text(text[:start] + "[design.dob]\n" + dob + text[end:])
    plant, design = PLANTS[name]
    return make_config(plant, design + "[design.dob]\n" + dob)


@pytest.mark.parametrize("name", list(PLANTS))
@pytest.mark.parametrize("method", [m for m in DOB_METHODS if m != "optimize"])
def test_no_method_returns_a_zero_or_silently_weak_gain(name: str, method: str) -> None:
    cfg = _plant_config(name, f'method = "{method}"\n')
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DesignWarning)
        try:
            r = design_with_diagnostics(cfg)
        except DesignError as exc:  # refused loudly, with the reason: acceptable, never silent
            assert "design" in str(exc) or "rho" in str(exc)
            return
    assert np.any(r.design.Kdist @ r.design.Lc), "a designed DOB must not be identically zero"
    q1 = float(np.linalg.svd(r.dob.dc_estimate_gain, compute_uv=False)[-1])
    msgs = [str(c.message) for c in caught if issubclass(c.category, DesignWarning)]
    if q1 < MIN_DC_ESTIMATE:
        assert any("estimates only" in m for m in msgs)
    # every violated robustness bound is reported
    assert set(r.warnings) >= set(msgs)


def test_min_radius_on_a_one_sample_delay_motor_is_not_zero() -> None:
    """Issue 14: min_radius gave Kdist = 0 ('fastest at k = 0') and the run said 'DOB on'."""
    r = _quiet(_plant_config("one-sample-delay", 'method = "min_radius"\n'))
    assert np.any(r.design.Kdist)
    assert float(r.dob.dc_estimate_gain[0, 0]) >= 0.5 - 1e-9
    assert any("min_radius" in w for w in r.dob.warnings)  # says the minimum is the floor itself


def test_dc_estimate_reaches_its_fraction_also_with_delay() -> None:
    for name in ("paper-dare", "one-sample-delay", "delay", "2x2"):
        try:
            r = _quiet(_plant_config(name, 'method = "dc_estimate"\ngain = 0.7\n'))
            fraction = 0.7
        except DesignError as exc:  # beyond the stable range: refused with the reachable maximum
            assert "no stable DOB gain estimates 0.7" in str(exc) and "at most" in str(exc)
            r = _quiet(_plant_config(name, 'method = "dc_estimate"\ngain = 0.4\n'))
            fraction = 0.4
        got = float(np.linalg.svd(r.dob.dc_estimate_gain, compute_uv=False)[-1])
        assert got == pytest.approx(fraction, abs=1e-9)


def test_stable_fraction_default_no_longer_lands_near_the_edge() -> None:
    r = _quiet(_plant_config("paper-step", 'method = "stable_fraction"\n'))
    assert r.dob.k_max is not None and r.dob.gain == pytest.approx(0.25 * r.dob.k_max)
    strong = _plant_config("paper-step", 'method = "stable_fraction"\ngain = 0.5\n')
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DesignWarning)
        design_with_diagnostics(strong)
    assert any("peak |S|" in str(c.message) for c in caught)  # 2.9 > 2: reported


def test_explicit_zero_kdist_with_the_dob_on_is_reported() -> None:
    r = _quiet(_plant_config("paper-step", "Kdist = [[0.0, 0.0]]\n"))
    assert any("the DOB does nothing" in w for w in r.warnings)


def test_the_run_path_does_not_import_scipy_optimize() -> None:
    """build_design (what run uses) of an explicit design needs no optimiser; only the methods that
    search (and `design`'s locus) import scipy.optimize."""
    import subprocess
    import sys

    code = (
        "import sys; from dob_hil.config import load_config; from dob_hil.scenarios import scenario_path; "
        "from dob_hil.design import build_design; "
        "[build_design(load_config(scenario_path(n))) for n in ('paper-step', 'paper-step-optimized')]; "
        "print('scipy.optimize' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    assert out.strip() == "False"
