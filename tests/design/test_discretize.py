"""ZOH discretisation and input-delay augmentation, checked against independent computations."""

from __future__ import annotations

import control
import numpy as np
import pytest

from dob_hil.design.discretize import (
    augment_input_delay,
    augmented_state_names,
    disturbance_input_matrix,
    zoh,
)
from dob_hil.design.linalg import frequency_response
from dob_hil.errors import DesignError


def test_zoh_agrees_with_python_control_c2d() -> None:
    A = np.array([[0.0, 1.0, 0.0], [-50.0, -3.0, 10.0], [0.0, 0.0, -200.0]])
    B = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 200.0]])
    Phi, Gam = zoh(A, B, 250_000)
    ref = control.c2d(control.ss(A, B, np.eye(3), 0), 250e-6, method="zoh")
    np.testing.assert_allclose(Phi, ref.A, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(Gam, ref.B, rtol=1e-12, atol=1e-14)


def test_zoh_of_the_paper_plant_matches_closed_form() -> None:
    """x' = [[0, 1], [0, -a]] x + [0, b] u has Phi12 = (1 - e^{-aT})/a, Gam1 = b (T - Phi12)/a."""
    a, b, T = 128.59, 2.1484e4, 300e-6
    Phi, Gam = zoh(np.array([[0.0, 1.0], [0.0, -a]]), np.array([[0.0], [b]]), 300_000)
    e = np.exp(-a * T)
    phi12 = (1 - e) / a
    np.testing.assert_allclose(Phi, [[1.0, phi12], [0.0, e]], rtol=1e-13)
    np.testing.assert_allclose(Gam[:, 0], [b * (T - phi12) / a, b * phi12], rtol=1e-12)


@pytest.mark.parametrize("delay", [1, 2, 3])
def test_delay_augmentation_is_a_pure_delay(delay: int) -> None:
    rng = np.random.default_rng(delay)
    n, m, p = 3, 2, 2
    Phi, Gam, C = rng.normal(size=(n, n)) * 0.4, rng.normal(size=(n, m)), rng.normal(size=(p, n))
    Pa, Ga, Ca = augment_input_delay(Phi, Gam, C, delay)
    assert Pa.shape == (n + delay * m, n + delay * m) and Ga.shape == (n + delay * m, m)
    # Transfer function: C_aug (zI - Phi_aug)^-1 Gam_aug = z^-d C (zI - Phi)^-1 Gam.
    z = np.exp(1j * np.array([0.1, 0.7, 2.0, 3.0]))
    got = frequency_response(Pa, Ga, Ca, np.zeros((p, m)), z)
    want = frequency_response(Phi, Gam, C, np.zeros((p, m)), z) * (z ** (-delay))[:, None, None]
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)
    # Time domain: simulating the augmented model equals the delayed plant, sample by sample.
    u = rng.normal(size=(30, m))
    x, xa = np.zeros(n), np.zeros(n + delay * m)
    for k in range(30):
        u_delayed = u[k - delay] if k >= delay else np.zeros(m)
        np.testing.assert_allclose(Ca @ xa, C @ x, atol=1e-12)
        x = Phi @ x + Gam @ u_delayed
        xa = Pa @ xa + Ga @ u[k]
    # The disturbance enters at the plant's own input, after the delay.
    Gw = disturbance_input_matrix(Pa, Ga, n, delay)
    np.testing.assert_array_equal(Gw[:n], Gam)
    assert not Gw[n:].any()


def test_zero_delay_is_the_identity_and_names_follow_the_state_order() -> None:
    Phi, Gam, C = np.eye(2), np.ones((2, 1)), np.ones((1, 2))
    Pa, Ga, Ca = augment_input_delay(Phi, Gam, C, 0)
    np.testing.assert_array_equal(Ca, C)
    np.testing.assert_array_equal(Pa, Phi)
    np.testing.assert_array_equal(Ga, Gam)
    assert augmented_state_names(("p", "v"), ("i", "j"), 2) == (
        "p",
        "v",
        "i(k-2)",
        "j(k-2)",
        "i(k-1)",
        "j(k-1)",
    )
    with pytest.raises(DesignError, match="input_delay_samples"):
        augment_input_delay(Phi, Gam, C, -1)
