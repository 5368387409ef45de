"""The reference state and feedforward for any plant (issue 14): x_ref = Nx r + Nv r', u_ref = Nu r.

The closed loop is simulated with the generated step and an exact discrete plant; steady-state errors
are checked against zero (no disturbance) and against the disturbance's own contribution (a constant
input disturbance with the DOB on: the reference adds no error of its own; a proportional DOB leaves
the residual (1 - Q(1)) w, see ``dob_hil.design.dob``).
"""

from __future__ import annotations

import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest

from dob_hil.config import Config, ReferenceConfig, load_config, parse_config_text
from dob_hil.control.reference import make_reference
from dob_hil.control.step import Gains, compile_step
from dob_hil.design import Design, build_design
from dob_hil.design.robustness import DesignWarning
from dob_hil.design.tracking import controller_gains, tracking_map
from dob_hil.log import read_log
from dob_hil.loop.session import RunOptions, run_session
from dob_hil.scenarios import scenario_path

# Motor and load coupled by a spring and damper; the encoder on the motor (output 0 = motor position).
TWO_MASS = """
[plant]
A = [[0.0, 1.0, 0.0, 0.0], [-4000.0, -52.0, 4000.0, 2.0], [0.0, 0.0, 0.0, 1.0], [8000.0, 4.0, -8000.0, -14.0]]
B = [0.0, 2.0e4, 0.0, 0.0]
C = [[1.0, 0.0, 0.0, 0.0]]
period_us = 300.0
state_names = ["motor_position", "motor_velocity", "load_position", "load_velocity"]
output_unit = "rev"
[design.estimator]
D1 = [[1.0e-3]]
[design.feedback]
q = 1.0e4
"""

# Two coupled axes with a spring to ground on axis 2 (so Nu != 0: holding position 2 needs current).
TWO_BY_TWO = """
[plant]
A = [[0.0, 1.0, 0.0, 0.0], [-40.0, -20.0, 40.0, 5.0], [0.0, 0.0, 0.0, 1.0], [30.0, 5.0, -60.0, -25.0]]
B = [[0.0, 0.0], [100.0, 10.0], [0.0, 0.0], [-5.0, 80.0]]
C = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
period_us = 1000.0
[design.estimator]
Gam1 = [[0.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.0, 1.0]]
D1 = [[0.01, 0.0], [0.0, 0.02]]
[design.feedback]
q = 1.0e4
R2 = [[1.0, 0.0], [0.0, 2.0]]
"""


def _config(text: str, extra: str = "") -> Config:
    return parse_config_text(textwrap.dedent(text) + extra)


def _design(text: str, extra: str = "") -> Design:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DesignWarning)
        return build_design(_config(text, extra))


def _simulate(
    design: Design, gains: Gains, r: np.ndarray, w: np.ndarray, x_ref: np.ndarray, steps: int
) -> np.ndarray:
    """Steady output of the loop: plant Phi x + Gam (u + w) (w at the plant input, before any delay)."""
    step = compile_step(gains, True)
    Phi, Gam, Gw, C = design.Phi, design.Gam, design.Gam_w, design.C
    x = np.zeros(design.n_states)
    x_bar: tuple[float, ...] = (0.0,) * design.n_states
    ref = tuple(float(v) for v in x_ref)
    for _ in range(steps):
        y = tuple(float(v) for v in C @ x)
        out = step.update(x_bar, y, ref)
        x_bar = step.predict(out.x_hat, out.u_cmd, out.u_dist)
        x = Phi @ x + Gam @ np.asarray(out.u_cmd) + Gw @ w
    return np.asarray(C @ x)


@pytest.mark.parametrize("plant", [TWO_MASS, TWO_BY_TWO], ids=["two-mass", "2x2"])
def test_step_has_zero_steady_state_error_with_and_without_a_constant_disturbance(plant: str) -> None:
    d = _design(plant)
    t = tracking_map(d)
    assert t.exact
    p, m = d.n_outputs, d.n_inputs
    r = np.linspace(1.0, 0.5, p)  # a step on every output
    gains = controller_gains(d)
    steps = 20000 if d.period_ns == 300_000 else 8000
    y = _simulate(d, gains, r, np.zeros(m), t.Nx @ r, steps)
    np.testing.assert_allclose(y, r, atol=1e-9)
    # With a constant input disturbance and the DOB on, the reference adds no error of its own:
    w = np.full(m, 0.1)
    y_w = _simulate(d, gains, r, w, t.Nx @ r, steps)
    y_w0 = _simulate(d, gains, np.zeros(p), w, t.Nx @ np.zeros(p), steps)
    np.testing.assert_allclose(y_w - r, y_w0, atol=1e-9)


def test_the_legacy_reference_misses_a_two_mass_plant() -> None:
    """What issue 14 found: x_ref = [r, 0, 0, 0] asks the load to stay at 0 while the motor goes to r."""
    d = _design(TWO_MASS)
    legacy = np.array([1.0, 0.0, 0.0, 0.0])
    y = _simulate(d, controller_gains(d), np.array([1.0]), np.zeros(1), legacy, 20000)
    assert abs(y[0] - 1.0) > 1e-3  # 27 counts short of the step
    np.testing.assert_allclose(tracking_map(d).Nx[:, 0], [1.0, 0.0, 1.0, 0.0])


def test_map_solves_the_steady_state_and_rate_equations() -> None:
    for plant in (TWO_MASS, TWO_BY_TWO):
        d = _design(plant)
        t = tracking_map(d)
        N, p = d.n_states, d.n_outputs
        np.testing.assert_allclose((d.Phi - np.eye(N)) @ t.Nx + d.Gam @ t.Nu, 0.0, atol=1e-9)
        np.testing.assert_allclose(d.C @ t.Nx, np.eye(p), atol=1e-12)
        np.testing.assert_allclose(d.C_cont @ t.Nv, 0.0, atol=1e-12)
        np.testing.assert_allclose(t.Kff @ t.Nx, t.Nu, atol=1e-9)
        np.testing.assert_allclose(t.Kff @ t.Nv, 0.0, atol=1e-9)
    assert np.any(tracking_map(_design(TWO_BY_TWO)).Nu)  # the spring to ground needs a holding current


def test_input_delay_states_get_the_steady_input() -> None:
    plant = TWO_BY_TWO.split("[design.estimator]", maxsplit=1)[0]
    d = _design(plant.replace("period_us = 1000.0", "period_us = 1000.0\ninput_delay_samples = 1"))
    t = tracking_map(d)
    np.testing.assert_allclose(t.Nx[4:], t.Nu, atol=1e-12)  # delayed inputs = u_ref at rest


@pytest.mark.parametrize("name", ["paper-step", "paper-sine"])
def test_the_papers_reference_and_step_are_unchanged_bit_for_bit(name: str) -> None:
    cfg = load_config(scenario_path(name))
    d = build_design(cfg)
    t = tracking_map(d)
    assert t.Nx.tolist() == [[1.0], [0.0]] and t.Nv.tolist() == [[0.0], [1.0]]
    assert not np.any(t.Kff) and not np.any(t.Nu)
    legacy = make_reference(cfg.reference, 2, cfg.plant.period_s)
    mapped = make_reference(cfg.reference, 2, cfg.plant.period_s, state_map=(t.Nx, t.Nv))
    for k in range(0, 3333, 7):
        a, b = legacy.at(k), mapped.at(k)
        assert np.asarray(a).tobytes() == np.asarray(b).tobytes()
    plain = Gains(d.Phi, d.Gam, d.C, d.Lc, d.Kc, d.Kdist)
    assert compile_step(controller_gains(d)).source == compile_step(plain).source


def test_mapped_sine_reference_carries_the_rate_terms() -> None:
    d = _design(TWO_MASS)
    t = tracking_map(d)
    ref = make_reference(
        ReferenceConfig(kind="sine", amplitude=1.0, frequency_hz=1.0), 4, d.period_s, state_map=(t.Nx, t.Nv)
    )
    x = np.asarray(ref.at(100))
    tt = 100 * d.period_s
    r, rd = np.sin(2 * np.pi * tt), 2 * np.pi * np.cos(2 * np.pi * tt)
    np.testing.assert_allclose(x, t.Nx[:, 0] * r + t.Nv[:, 0] * rd, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(t.Nv[[0, 1, 3], 0], [0.0, 1.0, 1.0], atol=1e-12)  # both masses move at r'


def test_two_mass_plant_settles_at_the_step_in_lockstep(tmp_path: Path) -> None:
    text = TWO_MASS + '\n[reference]\nkind = "step"\nposition = 1.0\n[run]\nduration_s = 1.0\n'
    cfg = _config(text)
    log = tmp_path / "two-mass.mcap"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DesignWarning)
        assert run_session(cfg, RunOptions(log_path=log)).exit_reason == "completed"
    s = read_log(log).samples
    # one count = 1e-4 rev: settled to within the encoder's resolution
    assert abs(float(s["position"][-1, 0]) - 1.0) <= 1.5e-4
    np.testing.assert_allclose(s["x_ref"][-1], [1.0, 0.0, 1.0, 0.0])
