"""The multi-axis simulated drive against its plant: one coupled plant, N nodes, one clock
(firmware_sim.axes), checked against python-control's discretisation of the same plant."""

from __future__ import annotations

import time

import control
import numpy as np
import pytest
from mimo_support import mimo_config, patient

from dob_hil.config import Config
from dob_hil.errors import DriveFault
from dob_hil.link.native_axes import MultiAxisNativeLink
from dob_hil.link.protocol import DriveState, FrameKind
from dob_hil.loop.inproc_bus import bus_pair
from firmware_sim.axes import AxesTruth, MultiAxisDrive, make_simulated_drive
from firmware_sim.drive import SimulatedDrive

NO_DISTURBANCE = {"amplitude_A = 0.2\n": "amplitude_A = 0.0\n", "amplitude_A = 0.15\n": "amplitude_A = 0.0\n"}


def _run_lockstep(config: Config, currents_A: tuple[float, float], periods: int) -> list[AxesTruth]:
    """Enable both axes, command ``currents_A`` for ``periods`` periods; the drive's truth per period."""
    truth: list[AxesTruth] = []
    host, drive_end = bus_pair("mimo-drive")
    drive = MultiAxisDrive(drive_end, config, truth_sink=truth.append)
    link = MultiAxisNativeLink(host, config.drive, 2)
    link.enable_lockstep(drive.service)
    for _ in range(periods):
        fb = link.receive_feedback(0)
        assert fb is not None
        codes, _, _ = link.quantize(currents_A)
        link.send_command(codes, fb.seq)
        drive.service()
    link.close()
    while drive.service():
        pass
    return truth


def test_truth_matches_python_controls_discretisation_of_the_coupled_plant() -> None:
    cfg = mimo_config(NO_DISTURBANCE)
    truth = _run_lockstep(cfg, (0.1, 0.0), 200)[:201]  # (the last: the period of the stop command)
    p = cfg.plant
    sysd = control.c2d(control.ss(p.A, p.B, np.eye(4), np.zeros((4, 2))), p.period_s, method="zoh")
    u = np.zeros((2, 201))
    u[0, :] = 205 / 2048  # the DAC code for 0.1 A, acting from sample 0 on
    expected = control.forced_response(sysd, U=u, X0=np.zeros(4)).states
    states = np.array([t.state for t in truth])
    assert [t.period_index for t in truth] == list(range(201))
    np.testing.assert_allclose(states.T, expected, rtol=1e-9, atol=1e-12)
    # the coupling is visible: motor 2 turns with no current of its own, dragged by the shaft
    assert all(t.applied_current_A[1] == 0.0 for t in truth)
    assert states[-1, 2] > 0.05 * states[-1, 0] > 0


def test_without_coupling_motor_2_stays_at_rest() -> None:
    cfg = mimo_config({**NO_DISTURBANCE, "[-4000.0, -148.59, 4000.0, 20.0]": "[0.0, -128.59, 0.0, 0.0]",
                       "[2000.0, 10.0, -2000.0, -74.3]": "[0.0, 0.0, 0.0, -64.3]"})  # fmt: skip
    truth = _run_lockstep(cfg, (0.1, 0.0), 100)
    assert truth[-1].state[0] > 0.01 and truth[-1].state[2] == 0.0


def test_each_disturbance_acts_on_its_input() -> None:
    cfg = mimo_config({"amplitude_A = 0.2\n": "amplitude_A = 0.0\n"})  # only input 1's 0.15 A, 6 Hz
    truth = _run_lockstep(cfg, (0.0, 0.0), 400)
    t_s = np.array([t.time_ns for t in truth]) * 1e-9
    w = np.array([t.disturbance_A for t in truth])
    np.testing.assert_allclose(w[:, 0], 0.0)
    np.testing.assert_allclose(w[:, 1], 0.15 * np.sin(2 * np.pi * 6.0 * t_s), atol=1e-12)
    assert abs(truth[-1].state[2]) > 0  # it moves motor 2 (and through the shaft motor 1)


def test_every_period_carries_one_feedback_per_node_with_one_sequence() -> None:
    cfg = mimo_config(NO_DISTURBANCE)
    host, drive_end = bus_pair("mimo-frames")
    drive = MultiAxisDrive(drive_end, cfg)
    link = MultiAxisNativeLink(host, cfg.drive, 2)
    seen: list[tuple[int, int]] = []
    original = host.recv

    def spy(timeout: float | None = None):  # type: ignore[no-untyped-def]
        msg = original(timeout)
        if msg is not None and msg.arbitration_id in (FrameKind.FEEDBACK + 1, FrameKind.FEEDBACK + 2):
            seen.append((msg.arbitration_id - FrameKind.FEEDBACK, msg.data[4]))
        return msg

    host.recv = spy  # type: ignore[method-assign]
    link.enable_lockstep(drive.service)
    for _ in range(300):
        fb = link.receive_feedback(0)
        assert fb is not None
        link.send_command(link.quantize((0.0, 0.0))[0], fb.seq)
        drive.service()
    link.close()
    assert len(seen) == 2 * 301
    assert all(seen[2 * k] == (1, k % 256) and seen[2 * k + 1] == (2, k % 256) for k in range(301))


def test_each_axis_has_its_own_watchdog() -> None:
    """Commands to both (arming both watchdogs), then to node 1 only: node 2's watchdog trips it,
    node 1 stays enabled."""
    cfg = mimo_config(NO_DISTURBANCE)
    host, drive_end = bus_pair("mimo-watchdog")
    drive = MultiAxisDrive(drive_end, cfg)
    link = MultiAxisNativeLink(host, cfg.drive, 2)
    link.enable_lockstep(drive.service)
    for _ in range(3):
        fb = link.receive_feedback(0)
        assert fb is not None
        link.send_command((10, 10), fb.seq)
        drive.service()
    with pytest.raises(DriveFault, match="node 2 reports a fault: WATCHDOG"):  # the link sees it
        for _ in range(cfg.drive.watchdog_periods + 2):
            fb = link.receive_feedback(0)
            assert fb is not None
            link.axes[0].send_command((10,), fb.seq)
            drive.service()
            drive.advance_period()  # node 2's command never comes: the clock runs on without it
    assert drive.axis_states == (DriveState.ENABLED, DriveState.FAULT)
    assert drive.axis_stats[0].commands_accepted >= cfg.drive.watchdog_periods + 3
    assert drive.axis_stats[1].commands_accepted == 3


def test_the_factory_gives_the_single_axis_drive_for_one_input(mimo: Config) -> None:
    from dob_hil.config import load_config
    from dob_hil.scenarios import scenario_path

    _, drive_end = bus_pair("mimo-factory")
    paper = load_config(scenario_path("paper-step"))
    assert isinstance(make_simulated_drive(drive_end, paper), SimulatedDrive)
    assert isinstance(make_simulated_drive(drive_end, mimo), MultiAxisDrive)


def test_the_real_time_drive_ticks_every_axis_on_one_clock(mimo: Config) -> None:
    cfg = patient(mimo_config(NO_DISTURBANCE), 1000)
    host, drive_end = bus_pair("mimo-rt", "virtual")
    truth: list[AxesTruth] = []
    try:
        with MultiAxisDrive(drive_end, cfg, clock="realtime", truth_sink=truth.append) as drive:
            link = MultiAxisNativeLink(host, cfg.drive, 2, period_ns=cfg.plant.period_ns)
            link.enable(30_000_000_000)
            answered = 0
            deadline = time.monotonic() + 60.0
            while answered < 200 and time.monotonic() < deadline:
                fb = link.receive_feedback(1_000_000_000)
                if fb is None:
                    continue
                assert not fb.fault  # (the first periods may precede node 2's enable)
                link.send_command(link.quantize((0.1, 0.0))[0], fb.seq)
                answered += 1
            link.close()
            assert answered == 200
            t_end = time.monotonic() + 30.0
            while DriveState.ENABLED in drive.axis_states and time.monotonic() < t_end:
                time.sleep(0.01)
            assert drive.axis_states == (DriveState.DISABLED, DriveState.DISABLED)
            assert drive.applied_currents_A == (0.0, 0.0)
        stats = drive.axis_stats
        assert stats[0].samples == stats[1].samples  # one clock: every tick latches both encoders
        assert all(s.commands_accepted >= 150 for s in stats)  # a loaded machine may lose a few
        moved = [t for t in truth if t.state[0] > 0]
        assert moved and moved[-1].state[2] > 0  # motor 2 dragged along by the shaft
    finally:
        host.shutdown()
        drive_end.shutdown()


@pytest.mark.parametrize("substeps", [1, 7])
def test_substeps_do_not_change_the_sampled_truth(substeps: int) -> None:
    base = _run_lockstep(mimo_config(NO_DISTURBANCE), (0.05, -0.05), 50)
    other = _run_lockstep(mimo_config({**NO_DISTURBANCE, "substeps = 10": f"substeps = {substeps}"}),
                          (0.05, -0.05), 50)  # fmt: skip
    np.testing.assert_allclose([t.state for t in other], [t.state for t in base], rtol=1e-9, atol=1e-13)


def test_the_axes_truth_datagram_round_trips_byte_for_byte() -> None:
    import struct

    from dob_hil.errors import ProtocolError
    from firmware_sim.truth import decode_axes_truth, decode_truth, encode_axes_truth

    truth = AxesTruth(7, 7_000_000, (1.0, 2.0, 3.0, 4.0), (0.1, -0.2), (0.5, 0.25), DriveState.ENABLED)
    data = encode_axes_truth(truth)
    head = b"FSGT" + bytes((2, 1)) + struct.pack("<HQqH", 4, 7, 7_000_000, 2) + bytes(6)
    assert data == head + struct.pack("<8d", 0.1, -0.2, 0.5, 0.25, 1.0, 2.0, 3.0, 4.0)
    assert decode_axes_truth(data) == truth
    with pytest.raises(ProtocolError, match="version 2, expected 1"):
        decode_truth(data)
    with pytest.raises(ProtocolError, match="4 states and 2 inputs need 96 bytes, got 95"):
        decode_axes_truth(data[:-1])
