"""The generated controller step against the straightforward numpy implementation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dob_hil.control.step import Gains, compile_step, numpy_predict, numpy_step
from dob_hil.errors import DesignError


def random_gains(rng: np.random.Generator, n: int, m: int, p: int, sparse: bool) -> Gains:
    def mat(r: int, c: int) -> np.ndarray:
        a = rng.normal(size=(r, c))
        if sparse:
            a[rng.random((r, c)) < 0.4] = 0.0  # exact zeros exercise the skipped terms
        return a

    return Gains(mat(n, n), mat(n, m), mat(p, n), mat(n, p), mat(m, n), mat(m, n))


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 5),
    m=st.integers(1, 3),
    p=st.integers(1, 3),
    seed=st.integers(0, 2**32 - 1),
    sparse=st.booleans(),
    dob=st.booleans(),
)
def test_generated_step_matches_numpy(n: int, m: int, p: int, seed: int, sparse: bool, dob: bool) -> None:
    rng = np.random.default_rng(seed)
    g = random_gains(rng, n, m, p, sparse)
    f = compile_step(g, dob_enabled=dob)
    x_bar = rng.normal(size=(n, 1))
    y = rng.normal(size=(p, 1))
    x_ref = rng.normal(size=(n, 1))
    out = f.update(tuple(x_bar.ravel()), tuple(y.ravel()), tuple(x_ref.ravel()))
    x_hat, u_fb, u_dist, u_cmd = numpy_step(g, dob, x_bar, y, x_ref)
    for got, want in ((out.x_hat, x_hat), (out.u_fb, u_fb), (out.u_dist, u_dist), (out.u_cmd, u_cmd)):
        np.testing.assert_allclose(np.array(got), want.ravel(), rtol=1e-12, atol=1e-12)
    u_applied = rng.normal(size=(m, 1))
    nxt = f.predict(out.x_hat, tuple(u_applied.ravel()), out.u_dist)
    want_next = numpy_predict(g, x_hat, u_applied, u_dist)
    np.testing.assert_allclose(np.array(nxt), want_next.ravel(), rtol=1e-12, atol=1e-12)


def test_dob_term_is_static_gain_on_innovation() -> None:
    """u_dist = Kdist (x_bar - x_hat) = -Kdist Lc (y - C x_bar): the paper's eq. 14."""
    rng = np.random.default_rng(1)
    g = random_gains(rng, 3, 1, 2, False)
    f = compile_step(g)
    x_bar, y = rng.normal(size=3), rng.normal(size=2)
    out = f.update(tuple(x_bar), tuple(y), (0.0, 0.0, 0.0))
    want = -(g.Kdist @ g.Lc @ (y - g.C @ x_bar))
    np.testing.assert_allclose(out.u_dist, want, rtol=1e-12)


def test_dob_off_gives_zero_u_dist_and_same_feedback() -> None:
    rng = np.random.default_rng(2)
    g = random_gains(rng, 2, 1, 1, False)
    on, off = compile_step(g, True), compile_step(g, False)
    args = ((0.3, -0.2), (0.1,), (1.0, 0.0))
    assert off.update(*args).u_dist == (0.0,)
    assert off.update(*args).u_fb == on.update(*args).u_fb


def test_repeatable_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    g = random_gains(rng, 2, 1, 1, False)
    a, b = compile_step(g), compile_step(g)
    args = ((0.3, -0.2), (0.1,), (1.0, 0.0))
    assert a.update(*args) == b.update(*args)


def test_generated_source_holds_no_numbers() -> None:
    """Coefficients enter as bound defaults, never as text of the generated code."""
    g = Gains(
        np.array([[1.0, 2.9e-4], [0.0, 0.96]]),
        np.array([[9.5e-4], [6.3]]),
        np.array([[1.0, 0.0]]),
        np.array([[0.75], [0.5]]),
        np.array([[107.42, 0.3]]),
        np.array([[18.0, 3.75]]),
    )
    src = compile_step(g).source
    for literal in ("0.75", "107.42", "18.0", "3.75", "6.3"):
        assert literal not in src


@pytest.mark.parametrize(
    ("field", "bad"),
    [("Lc", np.zeros((3, 1))), ("Kc", np.zeros((1, 3))), ("Kdist", np.array([[np.inf, 0.0]]))],
)
def test_wrong_shapes_and_non_finite_are_refused(field: str, bad: np.ndarray) -> None:
    base = dict(
        Phi=np.eye(2), Gam=np.ones((2, 1)), C=np.array([[1.0, 0.0]]), Lc=np.ones((2, 1)),
        Kc=np.ones((1, 2)), Kdist=np.ones((1, 2)),
    )  # fmt: skip
    base[field] = bad
    with pytest.raises(DesignError, match=field):
        compile_step(Gains(**base))
