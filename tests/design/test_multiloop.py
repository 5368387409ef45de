"""Multiloop (simultaneous) and loop-at-a-time balanced disk margins of MIMO loops (issue 15), checked
against independent computations: python-control interconnections of the run-time equations
(``helpers.runtime_interconnection``) with ``control.feedback``, ``stability_margins`` and
``disk_margins``; mu from its definition (the smallest diagonal Delta making I - M Delta singular);
and the structural facts SISO = loop-at-a-time, decoupled = worst loop, coupled <= every loop."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import control
import numpy as np
import pytest
import scipy.optimize

from dob_hil.commands.design import write_design_outputs
from dob_hil.config import Config
from dob_hil.design import Design, design_with_diagnostics
from dob_hil.design.analysis import analyze
from dob_hil.design.linalg import frequency_grid_hz, max_singular_value
from dob_hil.design.loops import design_loop_response
from dob_hil.design.multiloop import (
    balanced_disk_gain_phase,
    balanced_sensitivity,
    mu_lower_bound,
    mu_upper_bound,
    multiloop_disk_margin,
    osborne_scaling,
    scaled_norm,
)
from dob_hil.design.report import format_report
from dob_hil.design.robustness import DesignWarning, DiskMargin, disk_margin

from .conftest import MIMO_DESIGN, MIMO_PLANT, make_config
from .helpers import runtime_interconnection, sub_system

DECOUPLED_PLANT = """
[plant]
A = [[0.0, 1.0, 0.0, 0.0], [-40.0, -20.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, -25.0]]
B = [[0.0, 0.0], [100.0, 0.0], [0.0, 0.0], [0.0, 80.0]]
C = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
period_us = 1000.0
"""


def _grid(d: Design, points: int = 1500) -> np.ndarray:
    return 2.0 * math.pi * frequency_grid_hz(d.period_ns, points)


def _quiet(cfg: Config, **kw: object) -> object:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DesignWarning)
        return design_with_diagnostics(cfg, **kw)  # type: ignore[arg-type]


def _mu_by_definition(M: np.ndarray) -> float:
    """1 / min{ max(|d1|, |d2|) : det(I - M diag(d1, d2)) = 0 } for a 2x2 M: d2 solved from d1
    (det = 1 - m11 d1 - m22 d2 + det(M) d1 d2), the min over complex d1 on a polar grid, refined by
    Nelder-Mead. Shares nothing with dob_hil.design.multiloop."""
    m11, m22, det = M[0, 0], M[1, 1], np.linalg.det(M)

    def cost(v: np.ndarray) -> float:
        d1 = complex(v[0], v[1])
        den = m22 - det * d1
        if abs(den) < 1e-300:
            return math.inf
        return max(abs(d1), abs((1.0 - m11 * d1) / den))

    r = np.geomspace(1e-3, 1e3, 241)
    phi = np.linspace(-math.pi, math.pi, 181)
    R, P = np.meshgrid(r, phi)
    d1 = R * np.exp(1j * P)
    den = m22 - det * d1
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.maximum(np.abs(d1), np.abs((1.0 - m11 * d1) / den))
    k = np.unravel_index(int(np.nanargmin(g)), g.shape)
    res = scipy.optimize.minimize(cost, [d1[k].real, d1[k].imag], method="Nelder-Mead",
                                  options={"xatol": 1e-13, "fatol": 1e-15, "maxiter": 20000})  # fmt: skip
    return 1.0 / min(float(res.fun), float(g[k]))


def _loop_at_a_time_pc(L: control.StateSpace, i: int) -> control.StateSpace:
    """Channel i of the MIMO loop L (negative feedback) broken, all others closed: control.feedback
    with a diagonal feedback gain that is 0 on channel i."""
    E = np.eye(L.ninputs)
    E[i, i] = 0.0
    return control.feedback(L, E)[i, i]


# --- mu bounds ------------------------------------------------------------------------------------------


def test_mu_of_a_scalar_is_its_magnitude_and_sigma_max() -> None:
    M = np.array([[[0.3 - 0.4j]], [[-2.0 + 0.0j]]])
    ub, _ = mu_upper_bound(M)
    np.testing.assert_allclose(ub, [0.5, 2.0], rtol=1e-15)
    np.testing.assert_allclose(ub, max_singular_value(M), rtol=1e-15)
    np.testing.assert_allclose(mu_lower_bound(M), [0.5, 2.0], rtol=1e-15)


def test_mu_bounds_bracket_mu_on_random_matrices() -> None:
    """rho(M) <= lower <= upper <= sigma_max(M); scaling invariance; 2x2 and 3x3 (mu = upper bound for
    up to three complex scalar blocks): lower and upper bounds agree; 2x2 equals mu by definition."""
    rng = np.random.default_rng(15)
    for m in (2, 3, 4):
        M = rng.normal(size=(6, m, m)) + 1j * rng.normal(size=(6, m, m))
        ub, x = mu_upper_bound(M)
        lb = mu_lower_bound(M)
        rho = np.max(np.abs(np.linalg.eigvals(M)), axis=1)
        assert np.all(rho <= lb * (1 + 1e-12)) and np.all(lb <= ub * (1 + 1e-9))
        assert np.all(ub <= max_singular_value(M) * (1 + 1e-12))
        np.testing.assert_allclose(scaled_norm(M, x), ub, rtol=1e-12)  # the returned D attains it
        # mu(D0 M D0^-1) = mu(M) and mu(c M) = |c| mu(M)
        d0 = np.exp(rng.normal(size=(6, m)))
        ub2, _ = mu_upper_bound(M * d0[:, :, None] / d0[:, None, :])
        np.testing.assert_allclose(ub2, ub, rtol=1e-7)
        np.testing.assert_allclose(mu_upper_bound((2.0 - 1.0j) * M)[0], math.sqrt(5.0) * ub, rtol=1e-7)
        if m <= 3:
            np.testing.assert_allclose(lb, ub, rtol=1e-6)
        if m == 2:
            for Mi, u in zip(M, ub, strict=True):
                assert _mu_by_definition(Mi) == pytest.approx(float(u), rel=1e-6)


def test_mu_of_a_diagonal_or_triangular_matrix_is_its_largest_diagonal_entry() -> None:
    """No coupling (diagonal) or one-way coupling (triangular): mu = max |m_ii|, although sigma_max is
    larger for the triangular one (D -> 0 or inf removes the off-diagonal entry)."""
    M = np.array([[[0.9, 0.0], [0.0, -0.4j]], [[0.9, 5.0], [0.0, -0.4j]]], dtype=np.complex128)
    ub, _ = mu_upper_bound(M)
    np.testing.assert_allclose(ub, [0.9, 0.9], rtol=1e-6)
    assert max_singular_value(M)[1] > 5.0
    np.testing.assert_allclose(mu_lower_bound(M), [0.9, 0.9], rtol=1e-9)


def test_osborne_balancing_equalises_off_diagonal_rows_and_columns() -> None:
    rng = np.random.default_rng(3)
    M = rng.normal(size=(4, 3, 3)) * np.exp(rng.normal(scale=3.0, size=(4, 3, 3)))
    x = osborne_scaling(M.astype(np.complex128), sweeps=60)
    d = np.exp(x)
    B = np.abs(M) * d[:, :, None] / d[:, None, :]
    off = ~np.eye(3, dtype=bool)
    rows = np.sqrt(np.sum((B * off) ** 2, axis=2))
    cols = np.sqrt(np.sum((B * off) ** 2, axis=1))
    np.testing.assert_allclose(rows, cols, rtol=1e-6)


# --- disk margins of the run-time loop ----------------------------------------------------------------


@pytest.mark.parametrize("name", ["paper", "delay"])
@pytest.mark.parametrize("dob", [True, False])
def test_siso_multiloop_margin_is_the_balanced_disk_margin(
    designs: dict[str, Design], name: str, dob: bool
) -> None:
    d = designs[name]
    w = _grid(d)
    Si = design_loop_response(d, w, dob).Si
    one = disk_margin(Si[:, 0, 0], w)
    multi = multiloop_disk_margin(Si, w)
    assert multi.alpha == pytest.approx(one.alpha, rel=1e-12)
    assert multi.gain_margin_db == pytest.approx(one.gain_margin_db, rel=1e-12)
    assert multi.phase_margin_deg == pytest.approx(one.phase_margin_deg, rel=1e-12)
    assert multi.at_hz == pytest.approx(one.at_hz, rel=1e-12)
    assert multi.alpha_upper == pytest.approx(multi.alpha, rel=1e-12)
    # refining the worst frequency between grid points can only find a larger |s - 1/2|
    refined = multiloop_disk_margin(Si, w, response=lambda x: design_loop_response(d, x, dob).Si)
    assert one.alpha * (1 - 1e-3) <= refined.alpha <= one.alpha * (1 + 1e-12)


@pytest.mark.parametrize("dob", [True, False])
def test_decoupled_plant_multiloop_margin_is_the_worst_loop(dob: bool) -> None:
    r = _quiet(make_config(DECOUPLED_PLANT, '[design.dob]\nmethod = "dc_loop_gain"\ngain = 0.5\n'))
    d = r.design  # type: ignore[attr-defined]
    w = _grid(d)
    Si = design_loop_response(d, w, dob).Si
    assert float(np.max(np.abs(Si[:, 0, 1]) + np.abs(Si[:, 1, 0]))) < 1e-12  # decoupled indeed
    loops = [disk_margin(Si[:, i, i], w) for i in range(2)]
    multi = multiloop_disk_margin(Si, w)
    assert abs(loops[0].alpha - loops[1].alpha) > 0.01  # the two axes differ: the min is a real choice
    assert multi.alpha == pytest.approx(min(dm.alpha for dm in loops), rel=1e-9)
    worst = min(loops, key=lambda dm: dm.alpha)
    assert multi.at_hz == pytest.approx(worst.at_hz, rel=1e-12)


@pytest.mark.parametrize("dob", [True, False])
def test_coupled_multiloop_margin_is_below_every_loop_at_a_time_margin(
    designs: dict[str, Design], dob: bool
) -> None:
    d = designs["mimo"]
    w = _grid(d)
    r = design_loop_response(d, w, dob)
    for F in (r.Si, r.S):
        multi = multiloop_disk_margin(F, w)
        loops = [disk_margin(F[:, i, i], w).alpha for i in range(2)]
        assert multi.alpha < min(loops)  # strictly: the coupling costs margin
        assert multi.alpha <= multi.alpha_upper <= multi.alpha * (1 + 1e-6)  # mu exact for 2 blocks
        # on the grid: the mu upper bound is at least the spectral radius everywhere
        M = balanced_sensitivity(F[::15])
        ub, _ = mu_upper_bound(M)
        assert np.all(ub >= np.max(np.abs(np.linalg.eigvals(M)), axis=1) * (1 - 1e-12))
        assert np.all(ub <= max_singular_value(M) * (1 + 1e-12))
        assert 1.0 / multi.alpha >= float(np.max(ub)) * (1 - 1e-12)


@pytest.mark.parametrize("dob", [True, False])
def test_mimo_margins_match_python_control_interconnection(
    designs: dict[str, Design], mimo_config: Config, dob: bool
) -> None:
    """Loop-at-a-time classical and disk margins at the plant input and output of the 2x2 loop, and
    the multiloop margin at the plant input, from a python-control interconnection of the run-time
    equations (control.feedback closes the other channel; stability_margins, disk_margins)."""
    d = designs["mimo"]
    result = _quiet(mimo_config, dob_enabled=dob)
    report = analyze(result, mimo_config).to_dict()  # type: ignore[arg-type]
    loop = report["loop_dob_on" if dob else "loop_dob_off"]
    w = _grid(d)
    L_in = -sub_system(runtime_interconnection(d, dob, open_at_plant_input=True), "u", "uin")
    L_out = -sub_system(runtime_interconnection(d, dob, open_at_plant_output=True), "y", "yin")
    for where, L in (("input", L_in), ("output", L_out)):
        for i in range(2):
            li = _loop_at_a_time_pc(L, i)
            gm, pm, _, wpc, wgc, _ = control.stability_margins(li)
            mine = loop[f"margins_plant_{where}"][i]
            assert mine["gain_margin_dB"] == pytest.approx(20 * math.log10(gm), abs=0.01)
            assert mine["phase_margin_deg"] == pytest.approx(pm, abs=0.01)
            assert mine["gain_margin_at_Hz"] == pytest.approx(wpc / (2 * math.pi), rel=1e-4)
            assert mine["phase_margin_at_Hz"] == pytest.approx(wgc / (2 * math.pi), rel=1e-4)
            dm_ref, dgm_ref, dpm_ref = control.disk_margins(li, w, skew=0.0)
            disk = loop[f"disk_margins_plant_{where}"][i]
            assert disk["alpha"] == pytest.approx(float(dm_ref), rel=1e-6)
            assert disk["gain_margin_dB"] == pytest.approx(float(dgm_ref), rel=1e-6)
            assert disk["phase_margin_deg"] == pytest.approx(float(dpm_ref), rel=1e-6)
        # multiloop: mu of python-control's balanced sensitivity (I + L)^-1 - I/2 on the same grid
        S_pc = control.feedback(control.ss([], [], [], np.eye(2), d.period_s), L)
        F = np.moveaxis(S_pc(np.exp(1j * w * d.period_s)), -1, 0)  # evaluated on the unit circle
        ub, _ = mu_upper_bound(balanced_sensitivity(F))
        multi = loop[f"multiloop_disk_margin_plant_{where}"]
        # the report refines the worst frequency between grid points: at most slightly smaller
        assert multi["alpha"] == pytest.approx(1.0 / float(np.max(ub)), rel=1e-4)
        assert multi["alpha"] <= 1.0 / float(np.max(ub)) * (1 + 1e-9)
        i_worst = int(np.argmax(ub))
        assert _mu_by_definition(balanced_sensitivity(F[i_worst : i_worst + 1])[0]) == pytest.approx(
            float(ub[i_worst]), rel=1e-6
        )
        assert all(multi["alpha"] < x["alpha"] for x in loop[f"disk_margins_plant_{where}"])


def test_disk_margin_json_has_low_and_high_gain_and_null_for_infinite() -> None:
    gm, pm = balanced_disk_gain_phase(0.5)
    assert gm == pytest.approx(20 * math.log10(1.25 / 0.75))
    assert pm == pytest.approx(2 * math.degrees(math.atan(0.25)))
    d = DiskMargin(0.5, gm, pm, 3.0).as_dict()
    assert d["gain_margin_low_dB"] == -gm and d["gain_margin_high_dB"] == gm
    inf = DiskMargin(2.5, *balanced_disk_gain_phase(2.5), 3.0).as_dict()
    assert inf["gain_margin_dB"] is None and inf["gain_margin_high_dB"] is None
    json.dumps(inf, allow_nan=False)


# --- report and warnings ----------------------------------------------------------------------------------


def test_mimo_report_tables_per_channel(mimo_config: Config, tmp_path: Path) -> None:
    report = write_design_outputs(mimo_config, tmp_path, quiet=True, plots=False)
    json.dumps(report, allow_nan=False)
    text = format_report(report)
    for needle in (
        "input 1 (i1)",
        "input 2 (i2)",
        "output 1 (p1)",
        "output 2 (p2)",
        "multiloop disk margin at the plant input (every channel perturbed at once)",
        "multiloop disk margin at the plant output",
        "peak sigma_max(S)",
        "mu bounds agree",
    ):
        assert needle in text, needle
    assert "plant input [0]" not in text  # the SISO layout is not used for a 2x2 loop
    for key in ("loop_dob_on", "loop_dob_off"):
        loop = report[key]
        nz = loop["noise_to_current"]
        assert len(nz["peak_A_per_count_per_input"]) == 2 == len(loop["delay_margin_per_input"])
        # each input's peak is at most the sigma_max peak (a row of K S), the largest one close to it
        assert max(nz["peak_A_per_count_per_input"]) <= nz["peak_A_per_count"] * (1 + 1e-12)
        assert max(nz["peak_A_per_count_per_input"]) >= 0.9 * nz["peak_A_per_count"]
        assert loop["delay_margin"]["s"] == min(x["s"] for x in loop["delay_margin_per_input"])
    assert report["input_names"] == ["i1", "i2"]


def test_siso_text_report_keeps_its_layout(paper_config: Config, tmp_path: Path) -> None:
    report = write_design_outputs(paper_config, tmp_path, quiet=True, plots=False)
    text = format_report(report)
    assert "disk margin (balanced) plant input [0]: +/-17.7" in text
    assert "multiloop" not in text and "input 1" not in text
    on = report["loop_dob_on"]
    assert on["multiloop_disk_margin_plant_input"]["alpha"] == pytest.approx(
        on["disk_margins_plant_input"][0]["alpha"], rel=1e-3
    )
    assert not any("multiloop" in w for w in report["warnings"])


def _multiloop_warnings(cfg: Config, dob: bool) -> list[str]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DesignWarning)
        r = design_with_diagnostics(cfg, dob_enabled=dob)
    msgs = [str(c.message) for c in caught if issubclass(c.category, DesignWarning)]
    assert set(msgs) == set(r.warnings)
    return [m for m in msgs if "multiloop" in m]


def test_multiloop_margin_below_the_configured_bound_warns(mimo_config: Config) -> None:
    """The 2x2 loop: multiloop disk GM +/-10.7 dB with the DOB, +/-7.9 dB without (loop at a time
    >= 10.8 and 8.0). The default bound (6 dB) passes; a configured 10.8 dB bound fails for both,
    9 dB only without the DOB; a 60 deg phase bound fails with it."""
    assert _multiloop_warnings(mimo_config, True) == []
    text = MIMO_DESIGN + "[design.optimize]\nmin_disk_gain_margin_dB = 10.8\n"
    on = _multiloop_warnings(make_config(MIMO_PLANT, text), True)
    off = _multiloop_warnings(make_config(MIMO_PLANT, text), False)
    assert len(on) == 1 and on[0].startswith("robustness with the DOB: multiloop disk gain margin")
    assert "< 10.8 dB (design.optimize.min_disk_gain_margin_dB)" in on[0]
    assert len(off) == 1 and "without the DOB" in off[0]
    nine = MIMO_DESIGN + "[design.optimize]\nmin_disk_gain_margin_dB = 9.0\n"
    assert _multiloop_warnings(make_config(MIMO_PLANT, nine), True) == []
    assert len(_multiloop_warnings(make_config(MIMO_PLANT, nine), False)) == 1
    phase = MIMO_DESIGN + "[design.optimize]\nmin_disk_phase_margin_deg = 60.0\n"
    (msg,) = _multiloop_warnings(make_config(MIMO_PLANT, phase), True)
    assert "multiloop disk phase margin" in msg and "< 60 deg" in msg


def test_a_configured_disk_bound_applies_to_a_siso_loop_too(paper_config: Config) -> None:
    from dataclasses import replace

    cfg = replace(paper_config, design=replace(paper_config.design, optimize=replace(
        paper_config.design.optimize, min_disk_gain_margin_dB=20.0)))  # fmt: skip
    (msg,) = _multiloop_warnings(cfg, True)
    assert "+/-17.7 dB < 20 dB" in msg


def test_optimize_bounds_the_multiloop_disk_margin_of_a_mimo_loop() -> None:
    """With a disk bound and two inputs the optimiser constrains the multiloop margin (not only the
    loop-at-a-time ones, which alone let it end at +/-8.85 dB multiloop for a 9 dB bound)."""
    text = MIMO_DESIGN + "[design.optimize]\nband_hz = [1.0, 10.0]\nmin_disk_gain_margin_dB = 9.0\n"
    cfg = make_config(MIMO_PLANT, text)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DesignWarning)
        r = design_with_diagnostics(cfg, optimize=True)
    assert not [c for c in caught if "multiloop" in str(c.message)]
    o = r.optimized
    assert o is not None and o.improved and o.merit.multiloop_input is not None
    assert o.merit.multiloop_input.gain_margin_db >= 9.0 * (1 - 1e-6)
    assert o.merit.disk_gain_margin_db == pytest.approx(9.0, rel=1e-3)  # the bound is active
    report = analyze(r, cfg).to_dict()
    multi = report["loop_dob_on"]["multiloop_disk_margin_plant_input"]
    assert multi["gain_margin_dB"] >= 9.0 * (1 - 1e-3)
    assert report["optimize"]["result"]["multiloop_disk_margin_plant_input"]["gain_margin_dB"] >= 9.0 - 1e-6


def test_mimo_design_plots_pass_the_plot_check(
    mimo_config: Config, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """The 2x2 design's PNGs pass the analyze plots' check (labels with units, legends covering no
    line): the per-input noise curves and the longer MIMO legends included."""
    import importlib.util

    import matplotlib.pyplot as plt

    from dob_hil.design import plots as design_plots

    spec = importlib.util.spec_from_file_location(
        "_plot_checks", Path(__file__).resolve().parents[1] / "analysis" / "test_plots.py"
    )
    assert spec is not None and spec.loader is not None
    checks = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(checks)
    kept: dict[str, object] = {}

    def keep(fig: object, out: Path, plt_: object) -> Path:
        kept[out.name] = fig
        return out

    monkeypatch.setattr(design_plots, "_save", keep)
    result = _quiet(mimo_config)
    design_plots.write_plots(analyze(result, mimo_config), tmp_path)  # type: ignore[arg-type]
    try:
        assert set(kept) >= {"sensitivity.png", "ltr.png"}
        for name, fig in kept.items():
            checks.check_figure(name, fig)
        labels = [ln.get_label() for ax in kept["sensitivity.png"].axes for ln in ax.get_lines()]  # type: ignore[attr-defined]
        assert any(lab.startswith("input 2 (i2), DOB on") for lab in labels)
    finally:
        for fig in kept.values():
            plt.close(fig)  # type: ignore[arg-type]


def test_mimo_classical_margin_warnings_name_the_input() -> None:
    """A 2x2 design with a DOB loop DC gain of 4 (phase margin ~26 deg at one input): the warnings
    say which input sets the loop-at-a-time margin, and the multiloop margin warns too."""
    text = MIMO_DESIGN.replace("gain = 0.5", "gain = 4.0")
    cfg = make_config(MIMO_PLANT, text)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DesignWarning)
        r = design_with_diagnostics(cfg)
    msgs = [m for m in r.warnings if m.startswith("robustness with the DOB: phase margin")]
    assert msgs, r.warnings
    report = analyze(r, cfg).to_dict()
    pms = [x["phase_margin_deg"] for x in report["loop_dob_on"]["margins_plant_input"]]
    worst = int(np.argmin(np.abs(pms)))
    assert msgs[0].endswith(f"at input {worst + 1} (i{worst + 1}) (loop at a time)")
    assert {str(c.message) for c in caught if issubclass(c.category, DesignWarning)} == set(r.warnings)
    delay = [m for m in r.warnings if "delay margin" in m]
    assert delay and f"at input {worst + 1} (i{worst + 1})" in delay[0]
    assert any(m.startswith("robustness with the DOB: multiloop disk gain margin") for m in r.warnings)
