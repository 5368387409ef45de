"""Loop transfer recovery at the plant output: the loop approaches the estimator's loop as q grows."""

from __future__ import annotations

import itertools
import math

import numpy as np

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
