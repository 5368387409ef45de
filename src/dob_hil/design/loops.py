"""The feedback loop of the run-time controller, in the frequency domain (paper sec. 3.5, eq. 12-13).

The controller exactly as ``dob_hil.control.step`` runs it (y measured, x_ref reference state)::

    x_hat  = x_bar + Lc (y - C x_bar)
    u_fb   = Kc (x_ref - x_hat)
    u_dist = Kdist (x_bar - x_hat)                 (Kdist = 0 with the DOB off)
    u      = u_fb + u_dist                         (applied to the plant, which also gets w)
    x_bar' = Phi x_hat + Gam (u - u_dist)  =  Phi x_hat + Gam u_fb

Eliminating x_hat (x_hat = (I - Lc C) x_bar + Lc y) gives a linear controller with state x_bar:

    x_bar' = Ak x_bar + Bk y + Gam Kc x_ref,     u = -(Ck x_bar + Dk y) + Kc x_ref
    Ak = (Phi - Gam Kc)(I - Lc C)        Bk = (Phi - Gam Kc) Lc
    Ck = Kc (I - Lc C) - Kdist Lc C      Dk = (Kc + Kdist) Lc

so u = -K(z) y with K(z) = Ck (zI - Ak)^-1 Bk + Dk. The DOB leaves the controller's poles (Ak) alone
and only changes its output map (Ck, Dk) -- again only through Kdist Lc. With the plant
P(z) = C (zI - Phi)^-1 Gam the loops are

    broken at the plant output:  Lo(z) = P(z) K(z)   (p x p)
    broken at the plant input:   Li(z) = K(z) P(z)   (m x m)

    S(z) = (I + Lo)^-1   (output sensitivity: output disturbance -> measured y)
    T(z) = Lo (I + Lo)^-1 (complementary sensitivity: -(measurement noise) -> y; S + T = I)

and an input disturbance w at the plant input (through Gam_w, see ``discretize``) reaches the output
as ``y = S(z) Pw(z) w`` with Pw(z) = C (zI - Phi)^-1 Gam_w.

The estimator's own loop, the LTR target (eq. 8), is Gtl(z) = C (zI - Phi)^-1 Phi Lc: the loop of
x_bar' = Phi x_bar + Gam u + Phi Lc (y - C x_bar) broken at the injection of y.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from dob_hil.design.linalg import CMatrix, Matrix, frequency_response, unit_circle_points

if TYPE_CHECKING:
    from dob_hil.design.artifact import Design


@dataclass(frozen=True)
class ControllerSS:
    """u = -K(z) y with K(z) = Ck (zI - Ak)^-1 Bk + Dk (reference omitted)."""

    Ak: Matrix
    Bk: Matrix
    Ck: Matrix
    Dk: Matrix


def controller_state_space(
    Phi: Matrix, Gam: Matrix, C: Matrix, *, Lc: Matrix, Kc: Matrix, Kdist: Matrix
) -> ControllerSS:
    """The run-time controller as a state-space feedback K(z) from y to -u (module docstring)."""
    N = Phi.shape[0]
    ImLC = np.eye(N) - Lc @ C
    PGK = Phi - Gam @ Kc
    return ControllerSS(
        Ak=np.asarray(PGK @ ImLC, dtype=np.float64),
        Bk=np.asarray(PGK @ Lc, dtype=np.float64),
        Ck=np.asarray(Kc @ ImLC - Kdist @ Lc @ C, dtype=np.float64),
        Dk=np.asarray((Kc + Kdist) @ Lc, dtype=np.float64),
    )


@dataclass(frozen=True)
class LoopResponse:
    """Frequency responses (first axis: frequency) of one loop configuration."""

    omega_rad_s: npt.NDArray[np.float64]
    P: CMatrix  # plant, u -> y (p x m)
    Pw: CMatrix  # plant, input disturbance w -> y (p x m)
    K: CMatrix  # controller, y -> -u (m x p)
    Lo: CMatrix  # loop at the plant output (p x p)
    Li: CMatrix  # loop at the plant input (m x m)
    S: CMatrix  # output sensitivity (p x p)
    T: CMatrix  # output complementary sensitivity (p x p)
    Si: CMatrix  # input sensitivity (m x m)
    disturbance: CMatrix  # w -> y (p x m)


def loop_response(
    Phi: Matrix,
    Gam: Matrix,
    Gam_w: Matrix,
    C: Matrix,
    *,
    Lc: Matrix,
    Kc: Matrix,
    Kdist: Matrix,
    period_s: float,
    omega_rad_s: npt.ArrayLike,
) -> LoopResponse:
    """All loop frequency responses at the angular frequencies ``omega_rad_s`` (rad/s)."""
    w = np.asarray(omega_rad_s, dtype=np.float64).ravel()
    z = unit_circle_points(w, period_s)
    p, m = C.shape[0], Gam.shape[1]
    P = frequency_response(Phi, Gam, C, np.zeros((p, m)), z)
    Pw = frequency_response(Phi, Gam_w, C, np.zeros((p, m)), z)
    k = controller_state_space(Phi, Gam, C, Lc=Lc, Kc=Kc, Kdist=Kdist)
    K = frequency_response(k.Ak, k.Bk, k.Ck, k.Dk, z)
    Lo = P @ K
    Li = K @ P
    Ip, Im = np.eye(p), np.eye(m)
    S = np.linalg.inv(Ip + Lo)
    T = Lo @ S
    Si = np.linalg.inv(Im + Li)
    return LoopResponse(
        omega_rad_s=w,
        P=P,
        Pw=Pw,
        K=K,
        Lo=Lo,
        Li=Li,
        S=np.asarray(S, dtype=np.complex128),
        T=np.asarray(T, dtype=np.complex128),
        Si=np.asarray(Si, dtype=np.complex128),
        disturbance=np.asarray(S @ Pw, dtype=np.complex128),
    )


def design_loop_response(design: Design, omega_rad_s: npt.ArrayLike, dob_enabled: bool) -> LoopResponse:
    """:func:`loop_response` of a :class:`Design`, with its Kdist or (DOB off) Kdist = 0."""
    Kdist = design.Kdist if dob_enabled else np.zeros_like(design.Kdist)
    return loop_response(
        design.Phi,
        design.Gam,
        design.Gam_w,
        design.C,
        Lc=design.Lc,
        Kc=design.Kc,
        Kdist=Kdist,
        period_s=design.period_s,
        omega_rad_s=omega_rad_s,
    )


def sensitivity_response(
    design: Design, omega_rad_s: np.ndarray, dob_enabled: bool
) -> tuple[CMatrix, CMatrix]:
    """(S, T) at the plant output (eq. 12-13) of the run-time controller, each complex with shape
    (len(omega_rad_s), p, p). ``omega_rad_s`` in rad/s (up to the Nyquist frequency pi / Ts)."""
    r = design_loop_response(design, omega_rad_s, dob_enabled)
    return r.S, r.T


def target_loop(Phi: Matrix, C: Matrix, Lc: Matrix, period_s: float, omega_rad_s: npt.ArrayLike) -> CMatrix:
    """Gtl(z) = C (zI - Phi)^-1 Phi Lc (eq. 8), the estimator's loop and the LTR target (p x p)."""
    z = unit_circle_points(omega_rad_s, period_s)
    p = C.shape[0]
    return frequency_response(Phi, Phi @ Lc, C, np.zeros((p, p)), z)


def loop_at_a_time(F: CMatrix, channel: int) -> npt.NDArray[np.complex128]:
    """The scalar loop seen at one channel of a loop-breaking point with all other loops closed:
    l_i = 1 / [(I + L)^-1]_ii - 1, given F = (I + L)^-1 (a sensitivity matrix)."""
    return np.asarray(1.0 / F[:, channel, channel] - 1.0, dtype=np.complex128)
