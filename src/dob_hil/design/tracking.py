"""The reference state and feedforward for any plant (Franklin, Powell, Workman: reference input).

For a commanded output r (p-vector) the plant's steady state, on the augmented discrete model, is

    [Phi - I  Gam] [Nx]   [0]
    [C        0  ] [Nu] = [I]         x_ref = Nx r,  u_ref = Nu r

(the delayed-input states of an augmented model come out as Nu r). For a moving reference the rate
terms come from the continuous plant (A, B, C_cont): with x = Nx r + Nv r', matching the r' terms of
x' = A x + B u gives

    [A  B] [Nv ]   [Nx]
    [C  0] [Nuv] = [0 ]               x_ref = Nx r + Nv r'

(Nv padded with zeros for the delay states). For the paper's plant (position, velocity with
C = [1, 0]) Nx = [1, 0]', Nv = [0, 1]' and Nu = 0: x_ref = [r, r'], exactly the paper's reference.
The velocity feedforward Nuv r' is not applied (the paper's controller has none); the static one is:
``u_ref = Nu r`` enters the step as ``Kff x_ref`` with ``Kff = [Nu 0] pinv([Nx Nv])`` (Kff Nx = Nu,
Kff Nv = 0), so the step's signature does not change and Kff = 0 (no code at all) when Nu = 0.

Entries within 1e-9 (relative) of an integer are snapped to it, so that structural zeros and ones are exact
(the paper's x_ref stays bit for bit what it was).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from dob_hil.control.step import Gains
from dob_hil.design.linalg import Matrix
from dob_hil.design.robustness import DesignWarning
from dob_hil.errors import DesignError

if TYPE_CHECKING:
    from dob_hil.design.artifact import Design

SNAP = 1e-9


@dataclass(frozen=True)
class TrackingMap:
    """x_ref = Nx r + Nv r' (N x p each), u_ref = Nu r (m x p), applied as Kff x_ref (m x N)."""

    Nx: Matrix
    Nv: Matrix
    Nu: Matrix
    Kff: Matrix
    exact: bool  # False: no steady state reaches every output exactly (least squares used)


def _snap(M: Matrix) -> Matrix:
    R = np.round(M)
    scale = max(1.0, float(np.max(np.abs(M)))) if M.size else 1.0
    return np.asarray(np.where(np.abs(M - R) <= SNAP * scale, R, M) + 0.0, dtype=np.float64)


def _solve(top: Matrix, rhs: Matrix) -> tuple[Matrix, bool]:
    sol, *_ = np.linalg.lstsq(top, rhs, rcond=None)
    resid = float(np.linalg.norm(top @ sol - rhs))
    return np.asarray(sol, dtype=np.float64), resid <= 1e-9 * max(1.0, float(np.linalg.norm(rhs)))


def tracking_map_of(
    Phi: Matrix, Gam: Matrix, C: Matrix, A: Matrix, B: Matrix, C_cont: Matrix, n_plant_states: int
) -> TrackingMap:
    """The reference map of an augmented discrete model and its continuous plant (module docstring)."""
    N, m, p = Phi.shape[0], Gam.shape[1], C.shape[0]
    n = n_plant_states
    top = np.block([[Phi - np.eye(N), Gam], [C, np.zeros((p, m))]])
    rhs = np.vstack([np.zeros((N, p)), np.eye(p)])
    sol, exact = _solve(top, rhs)
    Nx, Nu = _snap(sol[:N]), _snap(sol[N:])
    cont = np.block([[A, B], [C_cont, np.zeros((p, m))]])
    rate, exact_rate = _solve(cont, np.vstack([Nx[:n], np.zeros((p, p))]))
    Nv = np.zeros((N, p))
    Nv[:n] = _snap(rate[:n])
    M = np.hstack([Nx, Nv])
    Kff = _snap(np.hstack([Nu, np.zeros_like(Nu)]) @ np.linalg.pinv(M)) if np.any(Nu) else np.zeros((m, N))
    if np.any(Nu) and not np.allclose(Kff @ M, np.hstack([Nu, np.zeros_like(Nu)]), atol=1e-9):
        raise DesignError("reference: the feedforward Nu r cannot be written as Kff x_ref for this plant")
    return TrackingMap(Nx, Nv, Nu, Kff, exact and exact_rate)


def tracking_map(design: Design) -> TrackingMap:
    """:func:`tracking_map_of` for a design; warns (DesignWarning) when no steady state reaches the
    commanded outputs exactly (more outputs than inputs, or a plant zero at z = 1)."""
    t = tracking_map_of(
        design.Phi, design.Gam, design.C, design.A, design.B, design.C_cont, design.n_plant_states
    )
    if not t.exact:
        warnings.warn(
            f"reference: no steady state of {design.name} puts every output at its reference (more "
            "outputs than inputs, or a plant zero at z = 1); the least-squares reference state is used",
            DesignWarning,
            stacklevel=2,
        )
    return t


def controller_gains(design: Design) -> Gains:
    """The step's gains for a design, with the reference feedforward Kff."""
    t = tracking_map(design)
    return Gains(design.Phi, design.Gam, design.C, design.Lc, design.Kc, design.Kdist, Kff=t.Kff)
