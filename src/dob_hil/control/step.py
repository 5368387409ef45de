"""The pure controller step: current estimator, state feedback and state-space disturbance observer.

Per sample k, with ``y`` the measured output and ``x_ref`` the reference state::

    e      = y - C x_bar                    innovation
    x_hat  = x_bar + Lc e                   current estimate           (paper eq. 5)
    u_fb   = Kc (x_ref - x_hat) + Kff x_ref state feedback (eq. 9) and the reference feedforward
                                            u_ref = Nu r written as Kff x_ref (dob_hil.design.tracking;
                                            Kff = 0, no code at all, for the paper's plant)
    u_dist = Kdist (x_bar - x_hat)          disturbance observer       (eq. 4; = -Kdist Lc e)
    u_cmd  = u_fb + u_dist                  -> the link limits and quantizes it -> u_applied
    x_bar' = Phi x_hat + Gam (u_applied - u_dist)     prediction driven by the input actually
                                                      applied minus u_dist (NOTES.md, saturation)

No I/O, no clock, no allocation beyond the result tuples: the same code runs in lockstep, in real
time, and in ``dob-hil replay --verify``, so a replay reproduces every command bit for bit.

Speed: the paper's 2-state step must take about a microsecond in CPython. A numpy version spends
~4 us in call overhead on 2x2 matrices, so :func:`compile_step` generates straight-line Python for
the design's dimensions. The generated source is built from the *dimensions only* (identifiers such
as ``Phi_0_1``); every coefficient enters as a default argument holding a Python float, so no data
from a config or a log is ever turned into code. :func:`numpy_step` is the straightforward numpy
implementation kept as the independent reference (tests) and the baseline (benchmarks).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

from dob_hil.errors import DesignError

Matrix = npt.NDArray[np.float64]
Vec = tuple[float, ...]


class StepOutput(NamedTuple):
    x_hat: Vec
    u_fb: Vec
    u_dist: Vec
    u_cmd: Vec


UpdateFn = Callable[[Vec, Sequence[float], Sequence[float]], StepOutput]
PredictFn = Callable[[Vec, Sequence[float], Vec], Vec]


@dataclass(frozen=True)
class StepFunctions:
    """``update(x_bar, y, x_ref) -> StepOutput`` and ``predict(x_hat, u_applied, u_dist) -> x_bar'``."""

    update: UpdateFn
    predict: PredictFn
    n_states: int
    n_inputs: int
    n_outputs: int
    source: str  # the generated code, for inspection


@dataclass(frozen=True)
class Gains:
    """The matrices the step needs (the augmented discrete model, the three gains and the optional
    reference feedforward ``Kff``, m x N; None means zero)."""

    Phi: Matrix
    Gam: Matrix
    C: Matrix
    Lc: Matrix
    Kc: Matrix
    Kdist: Matrix
    Kff: Matrix | None = None

    def check(self) -> None:
        n = self.Phi.shape[0]
        m = self.Gam.shape[1]
        p = self.C.shape[0]
        want = {
            "Phi": (n, n),
            "Gam": (n, m),
            "C": (p, n),
            "Lc": (n, p),
            "Kc": (m, n),
            "Kdist": (m, n),
            "Kff": (m, n),
        }
        for name, shape in want.items():
            value = getattr(self, name)
            if value is None:
                continue
            if value.shape != shape:
                raise DesignError(f"{name}: expected shape {shape[0]}x{shape[1]}, got {value.shape}")
            if not np.all(np.isfinite(value)):
                raise DesignError(f"{name}: contains a non-finite value")


def _sum(terms: list[str]) -> str:
    return " + ".join(terms) if terms else "0.0"


def _tuple(names: list[str]) -> str:
    return "(" + "".join(f"{v}, " for v in names) + ")"


def compile_step(gains: Gains, dob_enabled: bool = True) -> StepFunctions:
    """Generate the straight-line step for these dimensions and bind the coefficients."""
    gains.check()
    n, m, p = gains.Phi.shape[0], gains.Gam.shape[1], gains.C.shape[0]
    Kdist = gains.Kdist if dob_enabled else np.zeros_like(gains.Kdist)

    coeffs: dict[str, float] = {}

    def coef(name: str, matrix: Matrix, i: int, j: int) -> str | None:
        value = float(matrix[i, j])
        if value == 0.0:
            return None  # exact zero: the term is skipped (same result bit for bit: +0.0 terms)
        key = f"{name}_{i}_{j}"
        coeffs[key] = value
        return key

    def dot(name: str, matrix: Matrix, row: int, vector: list[str]) -> str:
        terms = []
        for j, v in enumerate(vector):
            c = coef(name, matrix, row, j)
            if c is not None:
                terms.append(f"{c} * {v}")
        return _sum(terms)

    xb = [f"xb{i}" for i in range(n)]
    ys = [f"y{i}" for i in range(p)]
    rs = [f"r{i}" for i in range(n)]
    xh = [f"xh{i}" for i in range(n)]
    es = [f"e{i}" for i in range(p)]

    up: list[str] = []
    up.append(f"    {', '.join(xb)}, = x_bar")
    up.append(f"    {', '.join(ys)}, = y")
    up.append(f"    {', '.join(rs)}, = x_ref")
    for i in range(p):
        up.append(f"    e{i} = y{i} - ({dot('C', gains.C, i, xb)})")
    for i in range(n):
        up.append(f"    xh{i} = xb{i} + ({dot('Lc', gains.Lc, i, es)})")
    for i in range(n):
        up.append(f"    d{i} = r{i} - xh{i}")
    Kff = gains.Kff if gains.Kff is not None else np.zeros_like(gains.Kc)
    for i in range(m):
        fb = dot("Kc", gains.Kc, i, [f"d{j}" for j in range(n)])
        ff = dot("Kff", Kff, i, rs)
        up.append(f"    fb{i} = {fb}" + (f" + ({ff})" if ff != "0.0" else ""))
    for i in range(n):
        up.append(f"    o{i} = xb{i} - xh{i}")
    for i in range(m):
        up.append(f"    ud{i} = {dot('Kdist', Kdist, i, [f'o{j}' for j in range(n)])}")
    up.append(
        "    return _new(_Out, ("
        + ", ".join(
            [
                _tuple(xh),
                _tuple([f"fb{i}" for i in range(m)]),
                _tuple([f"ud{i}" for i in range(m)]),
                _tuple([f"fb{i} + ud{i}" for i in range(m)]),
            ]
        )
        + "))"
    )

    pr: list[str] = []
    pr.append(f"    {', '.join(xh)}, = x_hat")
    pr.append(f"    {', '.join(f'ua{i}' for i in range(m))}, = u_applied")
    pr.append(f"    {', '.join(f'ud{i}' for i in range(m))}, = u_dist")
    for i in range(m):
        pr.append(f"    v{i} = ua{i} - ud{i}")
    for i in range(n):
        phi = dot("Phi", gains.Phi, i, xh)
        gam = dot("Gam", gains.Gam, i, [f"v{j}" for j in range(m)])
        pr.append(f"    xn{i} = ({phi}) + ({gam})")
    pr.append(f"    return {_tuple([f'xn{i}' for i in range(n)])}")

    defaults = "".join(f", {k}={k}" for k in coeffs)
    source = (
        f"def update(x_bar, y, x_ref, _Out=_Out, _new=_new{defaults}):\n"
        + "\n".join(up)
        + f"\n\n\ndef predict(x_hat, u_applied, u_dist{defaults}):\n"
        + "\n".join(pr)
        + "\n"
    )
    # The namespace holds only the coefficient floats (bound as defaults) and the result type.
    # (the StepOutput is made with tuple.__new__: NamedTuple's own __new__ is a Python call)
    namespace: dict[str, Any] = {"_Out": StepOutput, "_new": tuple.__new__, **coeffs}
    run_generated(source, "<dob_hil.control.step generated>", namespace)
    return StepFunctions(namespace["update"], namespace["predict"], n, m, p, source)


def run_generated(source: str, filename: str, namespace: dict[str, Any]) -> None:
    """Define the functions of generated ``source`` in ``namespace``: the source tree's one
    ``exec``. Only for source built from dimensions and fixed identifiers, with every value
    bound through ``namespace`` (this module's step; :mod:`dob_hil.log.packers`' record packing,
    built from the log layout's field names and array sizes)."""
    exec(compile(source, filename, "exec"), namespace)


def numpy_step(
    gains: Gains, dob_enabled: bool, x_bar: Matrix, y: Matrix, x_ref: Matrix
) -> tuple[Matrix, Matrix, Matrix, Matrix]:
    """Straightforward numpy version of ``update`` (column vectors): x_hat, u_fb, u_dist, u_cmd."""
    x_hat = x_bar + gains.Lc @ (y - gains.C @ x_bar)
    u_fb = gains.Kc @ (x_ref - x_hat)
    if gains.Kff is not None:
        u_fb = u_fb + gains.Kff @ x_ref
    u_dist = gains.Kdist @ (x_bar - x_hat) if dob_enabled else np.zeros((gains.Gam.shape[1], 1))
    return x_hat, u_fb, u_dist, u_fb + u_dist


def numpy_predict(gains: Gains, x_hat: Matrix, u_applied: Matrix, u_dist: Matrix) -> Matrix:
    """Straightforward numpy version of ``predict``."""
    result: Matrix = gains.Phi @ x_hat + gains.Gam @ (u_applied - u_dist)
    return result
