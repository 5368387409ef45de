"""Zero-order-hold discretisation and input-delay augmentation (paper sec. 3.1 and its remark).

ZOH at period Ts of ``x' = A x + B u``:  ``Phi = e^{A Ts}``, ``Gam = int_0^Ts e^{A s} ds B``, both read
off one matrix exponential ``expm([[A, B], [0, 0]] Ts) = [[Phi, Gam], [0, I]]`` (Van Loan).

An input delay of d samples, ``x(k+1) = Phi x(k) + Gam u(k-d)``, is handled by carrying the delayed
inputs as states (the paper's "augmenting the delayed control as an additional state"):

    x_aug(k) = [x(k); u(k-d); u(k-d+1); ...; u(k-1)]            (n + d m states)

    Phi_aug = [[Phi, Gam, 0, ..., 0],      Gam_aug = [0; 0; ...; 0; I],      C_aug = [C, 0, ..., 0]
               [0,   0,   I, ..., 0],
               ...
               [0,   0,   0, ..., I],
               [0,   0,   0, ..., 0]]

so u(k) enters the last block and reaches the plant d samples later. The rest of the design works
on (Phi_aug, Gam_aug, C_aug). An input disturbance w acts at the plant's own input (after the delay):
``x(k+1) = Phi x(k) + Gam (u(k-d) + w(k))``, i.e. through ``Gam_w = [Gam; 0; ...; 0]``.
"""

from __future__ import annotations

import numpy as np

from dob_hil.design.linalg import Matrix
from dob_hil.errors import DesignError


def zoh(A: Matrix, B: Matrix, period_ns: int) -> tuple[Matrix, Matrix]:
    """ZOH discretisation of (A, B) at ``period_ns``: returns (Phi, Gam)."""
    import scipy.linalg

    if period_ns <= 0:
        raise DesignError(f"plant.period: must be > 0 ns, got {period_ns}")
    n, m = A.shape[0], B.shape[1]
    M = np.zeros((n + m, n + m))
    M[:n, :n] = A
    M[:n, n:] = B
    try:
        with np.errstate(over="ignore", invalid="ignore"):
            E = scipy.linalg.expm(M * (period_ns * 1e-9))
    except (np.linalg.LinAlgError, ValueError, OverflowError) as exc:
        raise DesignError(
            f"plant: the ZOH discretisation of A, B at {period_ns / 1e3:g} us failed ({exc}); "
            "|A| * Ts is too large"
        ) from None
    if not np.all(np.isfinite(E)):
        raise DesignError(
            f"plant: the ZOH discretisation of A, B at {period_ns / 1e3:g} us overflows "
            f"(|A| * Ts = {np.abs(M).max() * period_ns * 1e-9:.3g}); check plant.A, plant.B and period_us"
        )
    Phi = np.array(E[:n, :n], dtype=np.float64)
    Gam = np.array(E[:n, n:], dtype=np.float64)
    return Phi, Gam


def augment_input_delay(
    Phi: Matrix, Gam: Matrix, C: Matrix, delay_samples: int
) -> tuple[Matrix, Matrix, Matrix]:
    """(Phi_aug, Gam_aug, C_aug) for an input delay of ``delay_samples`` (see the module docstring)."""
    if delay_samples < 0:
        raise DesignError(f"plant.input_delay_samples: must be >= 0, got {delay_samples}")
    if delay_samples == 0:
        return Phi.copy(), Gam.copy(), C.copy()
    n, m, p = Phi.shape[0], Gam.shape[1], C.shape[0]
    N = n + delay_samples * m
    Phi_a = np.zeros((N, N))
    Phi_a[:n, :n] = Phi
    Phi_a[:n, n : n + m] = Gam  # the oldest stored input u(k-d) drives the plant
    for j in range(delay_samples - 1):  # shift register: u(k-d+j+1) moves into slot j
        r = n + j * m
        Phi_a[r : r + m, r + m : r + 2 * m] = np.eye(m)
    Gam_a = np.zeros((N, m))
    Gam_a[N - m :, :] = np.eye(m)
    C_a = np.zeros((p, N))
    C_a[:, :n] = C
    return Phi_a, Gam_a, C_a


def disturbance_input_matrix(
    Phi_aug: Matrix, Gam_aug: Matrix, n_plant_states: int, delay_samples: int
) -> Matrix:
    """Gam_w: how an input disturbance at the plant's own input (after the delay) enters x_aug."""
    if delay_samples == 0:
        return Gam_aug.copy()
    n, m = n_plant_states, Gam_aug.shape[1]
    Gam_w = np.zeros_like(Gam_aug)
    Gam_w[:n, :] = Phi_aug[:n, n : n + m]
    return Gam_w


def augmented_state_names(
    state_names: tuple[str, ...], input_names: tuple[str, ...], delay_samples: int
) -> tuple[str, ...]:
    """Names of x_aug: the plant's states, then ``<input>(k-d)`` ... ``<input>(k-1)``."""
    names = list(state_names)
    for lag in range(delay_samples, 0, -1):
        names.extend(f"{u}(k-{lag})" for u in input_names)
    return tuple(names)
