"""The paper's "model output": the nominal closed loop driven by the logged reference.

The discrete plant of the design (``x' = Phi x + Gam u``, ``y = C x``) under the same controller
step as the run (:func:`dob_hil.control.step.compile_step`, same DOB setting), fed the logged
``x_ref``, with no disturbance, no noise and no DAC quantization. The drive's current limit is
kept (it is part of the nominal system: without it the paper's step command would ask for
~100 A), applied as a plain clip. Plant and estimator start from the logged first ``x_bar``.

Without disturbance the estimator is exact, so the DOB's output stays zero and the model output
does not depend on the DOB setting; the DOB only changes how close the plant comes to it.

A tight Python loop over the generated step (a few microseconds per sample): a million samples
take a few seconds, so it runs only when plots are wanted.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from dob_hil.control.step import compile_step
from dob_hil.design import Design
from dob_hil.design.tracking import controller_gains

FloatArray = npt.NDArray[np.float64]


def nominal_output(
    design: Design,
    x_ref: FloatArray,
    *,
    dob_enabled: bool,
    current_limit_A: float | None,
    x0: FloatArray | None = None,
) -> FloatArray:
    """Model output y (len(x_ref) x p) of the nominal closed loop (module docstring)."""
    step = compile_step(controller_gains(design), dob_enabled)  # with the reference feedforward
    update, predict = step.update, step.predict
    n_samples = len(x_ref)
    p, m = design.n_outputs, design.n_inputs
    C_rows = [tuple(float(c) for c in row) for row in design.C]
    limit = float(current_limit_A) if current_limit_A is not None else float("inf")
    zero_u = (0.0,) * m
    x: tuple[float, ...] = tuple(float(v) for v in x0) if x0 is not None else (0.0,) * design.n_states
    x_bar = x
    y_out = np.empty((n_samples, p))
    refs = [tuple(row) for row in np.asarray(x_ref, dtype=np.float64).tolist()]
    for k in range(n_samples):
        y = tuple(sum(c * v for c, v in zip(row, x, strict=True)) for row in C_rows)
        y_out[k] = y
        out = update(x_bar, y, refs[k])
        u = tuple(min(max(v, -limit), limit) for v in out.u_cmd)
        x_bar = predict(out.x_hat, u, out.u_dist)
        x = predict(x, u, zero_u)  # the plant: Phi x + Gam u
    return y_out
