"""Independent reference implementations for the design tests.

``runtime_interconnection`` builds the closed loop with python-control from primitive blocks that
follow the run-time controller equations literally (one unit delay for x_bar, static gains and
summing junctions), with the physical plant and an explicit delay line on its input -- none of the
algebra of ``dob_hil.design.loops`` is reused. ``simulate_runtime`` steps the same equations in
plain numpy.
"""

from __future__ import annotations

from typing import Any

import control
import numpy as np

from dob_hil.design import Design
from dob_hil.design.discretize import zoh


def _labels(name: str, count: int) -> list[str]:
    """Signal names as python-control's summing junctions spell them (a scalar signal has no index)."""
    return [name] if count == 1 else [f"{name}[{i}]" for i in range(count)]


def _sum(inputs: list[str], output: str, count: int, name: str) -> Any:
    if count == 1:
        return control.summing_junction(inputs=inputs, output=output, name=name)
    return control.summing_junction(inputs=inputs, output=output, dimension=count, name=name)


def _match(labels: list[str], name: str) -> list[int]:
    return [i for i, lab in enumerate(labels) if lab == name or lab.startswith(name + "[")]


def _gain(D: np.ndarray, inputs: list[str], outputs: list[str], dt: float, name: str) -> Any:
    return control.ss(
        np.zeros((0, 0)),
        np.zeros((0, D.shape[1])),
        np.zeros((D.shape[0], 0)),
        D,
        dt,
        inputs=inputs,
        outputs=outputs,
        name=name,
    )


def runtime_interconnection(
    design: Design,
    dob_enabled: bool,
    *,
    open_at_plant_input: bool = False,
    open_at_plant_output: bool = False,
) -> Any:
    """Closed loop with inputs w (input disturbance), d (output disturbance) and outputs y (measured,
    = plant output + d), yp (plant output), u (controller command), ud (u_dist). With
    ``open_at_plant_input`` the plant is driven by an external input ``uin`` instead of u; with
    ``open_at_plant_output`` the controller reads an external input ``yin`` instead of y."""
    dt = design.period_s
    d = design.input_delay_samples
    m, p, N = design.n_inputs, design.n_outputs, design.n_states
    Phi0, Gam0 = zoh(np.asarray(design.A), np.asarray(design.B), design.period_ns)
    Phi, Gam, C, Lc, Kc = design.Phi, design.Gam, design.C, design.Lc, design.Kc
    Kdist = design.Kdist if dob_enabled else np.zeros_like(design.Kdist)
    blocks = [
        control.ss(
            Phi0,
            Gam0,
            design.C_cont,
            np.zeros((p, m)),
            dt,
            inputs=_labels("ua", m),
            outputs=_labels("yp", p),
            name="plant",
        ),
        _sum(["yp", "d"], "y", p, "sensor"),
        _sum(["udel", "w"], "ua", m, "actuator"),
    ]
    drive = "uin" if open_at_plant_input else "u"
    # Delay line: d unit delays between the command and the plant input.
    if d == 0:
        blocks.append(_gain(np.eye(m), _labels(drive, m), _labels("udel", m), dt, "nodelay"))
    else:
        A = np.zeros((d * m, d * m))
        A[m:, :-m] = np.eye((d - 1) * m)
        B = np.zeros((d * m, m))
        B[:m] = np.eye(m)
        Cd = np.zeros((m, d * m))
        Cd[:, -m:] = np.eye(m)
        blocks.append(
            control.ss(
                A,
                B,
                Cd,
                np.zeros((m, m)),
                dt,
                inputs=_labels(drive, m),
                outputs=_labels("udel", m),
                name="delay",
            )
        )
    # The controller, literally: x_bar is the state of a unit delay fed by x_bar_next.
    blocks += [
        control.ss(
            np.zeros((N, N)),
            np.eye(N),
            np.eye(N),
            np.zeros((N, N)),
            dt,
            inputs=_labels("xbn", N),
            outputs=_labels("xb", N),
            name="x_bar",
        ),
        # x_hat = x_bar + Lc (y - C x_bar)
        _gain(
            np.hstack([np.eye(N) - Lc @ C, Lc]),
            _labels("xb", N) + _labels("yin" if open_at_plant_output else "y", p),
            _labels("xh", N),
            dt,
            "upd",
        ),
        # u_fb = Kc (x_ref - x_hat), x_ref = 0
        _gain(-Kc, _labels("xh", N), _labels("ufb", m), dt, "fb"),
        # u_dist = Kdist (x_bar - x_hat)
        _gain(np.hstack([Kdist, -Kdist]), _labels("xb", N) + _labels("xh", N), _labels("ud", m), dt, "dob"),
        _sum(["ufb", "ud"], "u", m, "cmd"),
        # x_bar' = Phi x_hat + Gam (u - u_dist)
        _gain(
            np.hstack([Phi, Gam, -Gam]),
            _labels("xh", N) + _labels("u", m) + _labels("ud", m),
            _labels("xbn", N),
            dt,
            "pred",
        ),
    ]
    inputs = ["w", "d"] + (["uin"] if open_at_plant_input else []) + (["yin"] if open_at_plant_output else [])
    return control.interconnect(blocks, inputs=inputs, outputs=["y", "yp", "u", "ud"], name="closed_loop")


def sub_system(sys: Any, out: str, inp: str) -> Any:
    """The subsystem of ``sys`` from the input signal ``inp`` to the output signal ``out``."""
    return sys[_match(sys.output_labels, out), _match(sys.input_labels, inp)]


def block(G: np.ndarray, sys: Any, out: str, inp: str) -> np.ndarray:
    """The (frequency, out, in) block of a frequency response array ``G`` (outputs, inputs, freq)."""
    oi, ii = _match(sys.output_labels, out), _match(sys.input_labels, inp)
    return np.moveaxis(G[np.ix_(oi, ii)], -1, 0)


def simulate_runtime(design: Design, w: np.ndarray, dob_enabled: bool) -> dict[str, np.ndarray]:
    """Step the run-time controller and the (augmented) plant for the input disturbance sequence ``w``
    (shape (k, m)); x_ref = 0. Returns y, u and u_dist histories."""
    Phi, Gam, C, Lc, Kc = design.Phi, design.Gam, design.C, design.Lc, design.Kc
    Kdist = design.Kdist if dob_enabled else np.zeros_like(design.Kdist)
    Gw = design.Gam_w
    x = np.zeros(design.n_states)
    x_bar = np.zeros(design.n_states)
    ys, us, uds = [], [], []
    for wk in w:
        y = C @ x
        x_hat = x_bar + Lc @ (y - C @ x_bar)
        u_fb = Kc @ (0.0 - x_hat)
        u_dist = Kdist @ (x_bar - x_hat)
        u = u_fb + u_dist
        x = Phi @ x + Gam @ u + Gw @ wk
        x_bar = Phi @ x_hat + Gam @ (u - u_dist)
        ys.append(y)
        us.append(u)
        uds.append(u_dist)
    return {"y": np.array(ys), "u": np.array(us), "u_dist": np.array(uds)}


def random_stable_design_inputs(
    rng: np.random.Generator, n: int, m: int, p: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A random (Phi, Gam, C) with spectral radius ~1.05 (some unstable modes), full-rank Gam and C."""
    Phi = rng.normal(size=(n, n))
    Phi *= 1.05 / max(abs(np.linalg.eigvals(Phi)))
    return Phi, rng.normal(size=(n, m)), rng.normal(size=(p, n))
