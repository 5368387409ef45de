"""Loop transfer recovery at the plant output: the loop approaches the estimator's loop as q grows."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from dob_hil.config import Config
from dob_hil.design import build_design
from dob_hil.design.linalg import frequency_grid_hz, frequency_response
from dob_hil.design.loops import target_loop
from dob_hil.design.ltr import ltr_report


def test_target_loop_is_the_estimator_loop(paper_config: Config) -> None:
    """Gtl is the loop of x_bar' = Phi x_bar + Phi Lc (y - C x_bar) broken at y: check at a few z
    against the closed estimator's error transfer (I + Gtl)^-1 = I - C (zI - Phi + Phi Lc C)^-1 Phi Lc."""
    d = build_design(paper_config)
    w = np.array([1.0, 100.0, 3000.0])
    Gtl = target_loop(d.Phi, d.C, d.Lc, d.period_s, w)
    z = np.exp(1j * w * d.period_s)
    closed = frequency_response(d.Phi - d.Phi @ d.Lc @ d.C, d.Phi @ d.Lc, d.C, np.zeros((1, 1)), z)
    np.testing.assert_allclose(1.0 / (1.0 + Gtl), 1.0 - closed, rtol=1e-9)


def test_recovery_error_falls_as_q_grows(paper_config: Config) -> None:
    d = build_design(paper_config)
    w = 2 * math.pi * frequency_grid_hz(d.period_ns, 600)
    q_values = (1.0, 1e2, 1e4, 1e6, 1e8, 1e10, 1e12)
    rep = ltr_report(
        d.Phi,
        d.Gam,
        d.C,
        d.Lc,
        Kc_design=d.Kc,
        R2=np.eye(1),
        q_values=q_values,
        period_s=d.period_s,
        omega_rad_s=w,
    )
    rows = rep.rows[:-1]
    assert [r.q for r in rows] == list(q_values)
    assert rep.rows[-1].label == "design Kc"
    weighted = [r.max_weighted_error for r in rows]
    at_cross = [r.relative_error_at_crossover for r in rows]
    assert all(b < a for a, b in itertools.pairwise(weighted))
    assert all(x is not None for x in at_cross)
    assert at_cross[-1] is not None and at_cross[-1] < 0.01  # recovered around the crossover
    assert rows[-1].recovered_to_hz is not None and rows[-1].recovered_to_hz > 100.0
    assert all(r.feedback_radius < 1.0 for r in rows)


def test_table_extends_q_until_recovery_in_the_band_and_agrees_with_the_plotted_loops(
    paper_config: Config,
) -> None:
    """Issue 15: every row read "recovered to -" because q stopped at 1e6; the table must end with
    recovery (or a reason) and its numbers must be those of the loops the plot draws."""
    from dob_hil.design.linalg import max_singular_value

    d = build_design(paper_config)
    w = 2 * math.pi * frequency_grid_hz(d.period_ns, 800)
    rep = ltr_report(d.Phi, d.Gam, d.C, d.Lc, Kc_design=d.Kc, R2=np.eye(1), q_values=(1.0, 1e3, 1e6),
                     period_s=d.period_s, omega_rad_s=w, band_hz=(0.1, 200.0))  # fmt: skip
    rows = rep.rows[:-1]
    assert rows[-1].recovered and not any(r.recovered for r in rows[:-1])
    assert rep.recovered_at_q == rows[-1].q and rows[-1].q is not None and rows[-1].q > 1e6
    assert [r.q for r in rows[:3]] == [1.0, 1e3, 1e6]
    assert all(b.q == 10 * a.q for a, b in itertools.pairwise(rows[2:]))  # type: ignore[operator]
    f = w / (2 * math.pi)
    band = (f >= 0.1) & (f <= 200.0)
    g = max_singular_value(rep.Gtl)
    for r in rep.rows:
        err = max_singular_value(r.Lo - rep.Gtl) / g
        assert r.band_relative_error == float(np.max(err[band]))
        assert r.recovered == (r.band_relative_error <= 0.1)
    assert any("sampling zero" in n for n in rep.notes)  # recovery cancels the zero near -1


def test_input_delay_is_stated_as_an_obstruction(delay_config: Config) -> None:
    d = build_design(delay_config)
    w = 2 * math.pi * frequency_grid_hz(d.period_ns, 400)
    rep = ltr_report(d.Phi, d.Gam, d.C, d.Lc, Kc_design=d.Kc, R2=np.eye(1), q_values=(1.0, 1e4),
                     period_s=d.period_s, omega_rad_s=w)  # fmt: skip
    assert rep.obstructions and "C Gam has rank 0 < 1" in rep.obstructions[0]
    assert [r.q for r in rep.rows[:-1]] == [1.0, 1e4]  # not extended: it cannot recover
    assert rep.recovered_at_q is None and any("no q recovers" in n for n in rep.notes)


def test_mimo_recovery_error_sees_the_weak_direction(mimo_config: Config) -> None:
    """For the 2x2 loop (cond(Gtl) ~ 130: one direction of the coupled plant has no stiffness) the
    error is sigma_max((Lo - Gtl) Gtl^-1): at q = 1e12 some input direction of Gtl is still off by more
    than 10 % in the band (at its lowest frequencies), although sigma_max(Lo - Gtl) / sigma_max(Gtl) is
    below 2 % there; recovery is reached one decade later."""
    from dob_hil.design.linalg import max_singular_value

    d = build_design(mimo_config)
    w = 2 * math.pi * frequency_grid_hz(d.period_ns, 800)
    band_hz = (float(w[0]) / (2 * math.pi), 137.0)  # the report's default: up to twice the crossover
    rep = ltr_report(d.Phi, d.Gam, d.C, d.Lc, Kc_design=d.Kc, R2=np.diag([1.0, 2.0]), q_values=(1e10, 1e12),
                     period_s=d.period_s, omega_rad_s=w, band_hz=band_hz)  # fmt: skip
    f = w / (2 * math.pi)
    band = (f >= band_hz[0]) & (f <= band_hz[1])
    row = rep.rows[1]
    assert row.q == 1e12 and not row.recovered
    E = row.Lo - rep.Gtl
    naive = max_singular_value(E) / max_singular_value(rep.Gtl)
    assert float(np.max(naive[band])) < 0.02
    # a direction that shows it: v = Gtl^-1 u with u the worst direction of E Gtl^-1
    mult = np.array([np.linalg.norm(E[i] @ np.linalg.inv(rep.Gtl[i]), 2) for i in range(f.size)])
    k = int(np.argmax(np.where(band, mult, 0.0)))
    X = E[k] @ np.linalg.inv(rep.Gtl[k])
    u = np.linalg.svd(X)[2][0].conj()
    v = np.linalg.solve(rep.Gtl[k], u)
    ratio = np.linalg.norm(E[k] @ v) / np.linalg.norm(rep.Gtl[k] @ v)
    assert ratio > 0.1
    assert row.band_relative_error == pytest.approx(float(ratio), rel=1e-9)
    assert rep.recovered_at_q == 1e13 and rep.rows[2].recovered
