"""A synthetic 2x2 log: the coupled two-axis plant of tests/design/conftest.py in closed loop with
the project's controller, simulated here and written with the project's log writer.

The loop follows :class:`dob_hil.loop.cycle.ControlCycle` sample by sample: the encoder-quantised
output, ``update(x_bar, y, x_ref)``, each axis's current through the drive's quantizer
(:class:`dob_hil.link.native.DacQuantizer`, one axis at a time), ``predict``; the plant is the
exact zero-order-hold discretisation of the continuous plant (scipy's expm) with the configured
disturbances added at its inputs. The arrays are returned too, so tests can check what analysis
derives from the log against a computation on the simulated arrays themselves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import scipy.linalg

from dob_hil.config import Config, parse_config_text
from dob_hil.control.reference import make_reference
from dob_hil.control.step import compile_step
from dob_hil.design import build_design
from dob_hil.design.tracking import controller_gains, tracking_map
from dob_hil.link.native import DacQuantizer
from dob_hil.log import LogWriter
from dob_hil.log.metadata import run_metadata
from dob_hil.log.schemas import FLAG_DOB_ON, FLAG_SATURATED, LogLayout

FloatArray = npt.NDArray[np.float64]

MIMO_TEXT = """
[meta]
name = "mimo-2x2-synthetic"

[plant]
A = [[0.0, 1.0, 0.0, 0.0], [-40.0, -20.0, 40.0, 5.0], [0.0, 0.0, 0.0, 1.0], [30.0, 5.0, -30.0, -25.0]]
B = [[0.0, 0.0], [100.0, 10.0], [0.0, 0.0], [-5.0, 80.0]]
C = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
period_us = 1000.0
state_names = ["p1", "v1", "p2", "v2"]
input_names = ["i1", "i2"]
output_names = ["p1", "p2"]
output_unit = "rev"

[design.estimator]
Gam1 = [[0.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.0, 1.0]]
D1 = [[0.01, 0.0], [0.0, 0.02]]
[design.feedback]
q = 1.0e4
R2 = [[1.0, 0.0], [0.0, 2.0]]
[design.dob]
method = "dc_loop_gain"
gain = 0.5

[drive]
current_limit_A = 3.0
encoder_counts_per_unit = 10000.0

[[sim.disturbance]]
kind = "sine"
amplitude_A = 0.4
frequency_hz = 2.0
input_index = 0
[[sim.disturbance]]
kind = "step"
amplitude_A = -0.3
start_s = 0.1
input_index = 1

[[reference.outputs]]
kind = "step"
position = 0.05
start_s = 0.05
[[reference.outputs]]
kind = "sine"
amplitude = 0.03
frequency_hz = 1.0

[run]
duration_s = 0.6
"""


@dataclass(frozen=True)
class MimoRun:
    """What was simulated, one row per sample (also what the log holds)."""

    config: Config
    path: Path
    x_true: FloatArray  # plant state at each sample
    y_true: FloatArray  # C x_true
    y_ref: FloatArray  # the commanded outputs r
    w_A: FloatArray  # disturbance at each input
    u_dist: FloatArray
    u_applied: FloatArray


def _disturbance(config: Config, t_s: float) -> list[float]:
    w = [0.0] * config.plant.n_inputs
    for d in config.sim.disturbances:
        if t_s < d.start_s:
            continue
        if d.kind == "sine":
            w[d.input_index] += d.amplitude_A * math.sin(2.0 * math.pi * d.frequency_hz * t_s + d.phase_rad)
        elif d.kind == "step":
            w[d.input_index] += d.amplitude_A
    return w


def write_mimo_log(path: Path, *, dob: bool, text: str = MIMO_TEXT) -> MimoRun:
    config = parse_config_text(text)
    design = build_design(config, dob_enabled=dob)
    tracking = tracking_map(design)
    step = compile_step(controller_gains(design), dob)
    N, m, p = step.n_states, step.n_inputs, step.n_outputs
    reference = make_reference(
        config.reference, N, config.plant.period_s, state_map=(tracking.Nx, tracking.Nv)
    )
    quantizer = DacQuantizer(config.drive)
    period_ns = config.plant.period_ns
    n_samples = round(config.run.duration_s * 1e9 / period_ns)
    A, B = design.A, design.B
    n = A.shape[0]
    M = scipy.linalg.expm(np.block([[A, B], [np.zeros((m, n + m))]]) * config.plant.period_s)
    Phi, Gam = M[:n, :n], M[:n, n:]
    C = design.C_cont
    cpu = config.drive.encoder_counts_per_unit
    layout = LogLayout(n_states=N, n_inputs=m, n_outputs=p, n_plant_states=n)
    run = run_metadata(
        mode="lockstep",
        bus="none (synthetic: tests/analysis/mimo_log_support.py)",
        period_ns=period_ns,
        layout=layout,
        planned_samples=str(n_samples),
        dob_enabled=str(dob).lower(),
        scenario=config.name,
        current_limit_A=repr(config.drive.current_limit_A),
        dac_lsb_A=repr(config.drive.dac_lsb_A),
        encoder_counts_per_unit=repr(cpu),
        missing_feedback_policy=config.run.missing_feedback_policy,
    )
    x = np.zeros(n)
    x_bar: tuple[float, ...] = (0.0,) * N
    rows: dict[str, list[list[float]]] = {k: [] for k in ("x", "y_ref", "w", "u_dist", "applied")}
    attachments = {"design.json": design.to_json().encode(), "config.toml": config.text.encode()}
    with LogWriter(path, layout, metadata={"run": run}, attachments=attachments) as log:
        for k in range(n_samples):
            t_ns = k * period_ns
            counts = tuple(round(float(v) * cpu) for v in C @ x)
            position = tuple(c / cpu for c in counts)
            x_ref = reference.at(k)
            out = step.update(x_bar, position, x_ref)
            axes = [quantizer.quantize((u,)) for u in out.u_cmd]
            codes = tuple(a[0][0] for a in axes)
            applied = tuple(a[1][0] for a in axes)
            saturated = any(a[2] for a in axes)
            w = _disturbance(config, k * config.plant.period_s)
            flags = (FLAG_DOB_ON if dob else 0) | (FLAG_SATURATED if saturated else 0)
            log.sample(
                t_ns, t_ns, t_ns, 0, counts, position, x_ref, out.x_hat, x_bar, out.u_fb, out.u_dist,
                out.u_cmd, applied, k, 1000, codes, k % 256, flags,
            )  # fmt: skip
            log.truth(t_ns, x.tolist(), w, applied, k, 1)
            rows["x"].append(x.tolist())
            rows["y_ref"].append(list(np.asarray(x_ref) @ design.C.T))
            rows["w"].append(w)
            rows["u_dist"].append(list(out.u_dist))
            rows["applied"].append(list(applied))
            x_bar = step.predict(out.x_hat, applied, out.u_dist)
            x = Phi @ x + Gam @ (np.asarray(applied) + np.asarray(w))
        log.flush(force=True)
    x_true = np.asarray(rows["x"])
    return MimoRun(
        config=config,
        path=path,
        x_true=x_true,
        y_true=x_true @ C.T,
        y_ref=np.asarray(rows["y_ref"]),
        w_A=np.asarray(rows["w"]),
        u_dist=np.asarray(rows["u_dist"]),
        u_applied=np.asarray(rows["applied"]),
    )
