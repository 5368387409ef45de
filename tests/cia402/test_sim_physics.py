"""Physics behind the CiA 402 drive: same plant motion as the native drive for the same current,
an exact ZOH check, torque quantization and clamping, and the timing contract at SYNC."""

from __future__ import annotations

import dataclasses
import itertools
import random

import can
import numpy as np
import pytest
import scipy.linalg
from sim_support import NODE, make_config, raw_rig, sdo_request, unique_channel

from dob_hil.link import protocol
from dob_hil.link.protocol import FrameKind, frame_id
from firmware_sim import SimulatedDrive
from firmware_sim.truth import GroundTruth

RPDO1, TPDO1 = 0x200 + NODE, 0x180 + NODE


def _rpdo(controlword: int, torque: int) -> bytes:
    return controlword.to_bytes(2, "little") + torque.to_bytes(2, "little", signed=True)


def _native_truths(config, codes: list[int]) -> tuple[list[GroundTruth], list[int]]:  # type: ignore[no-untyped-def]
    """The native drive (lockstep) commanded ``codes`` (DAC counts), one per sample."""
    config = dataclasses.replace(config, drive=dataclasses.replace(config.drive, profile="native"))
    channel = unique_channel()
    host = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    truths: list[GroundTruth] = []
    counts: list[int] = []
    try:
        drive = SimulatedDrive(bus, config, truth_sink=truths.append)

        def send(kind: FrameKind, payload: bytes) -> None:
            host.send(can.Message(arbitration_id=frame_id(kind, NODE), data=payload, is_extended_id=False))
            drive.service()
            while (msg := host.recv(0.0)) is not None:
                if msg.arbitration_id == frame_id(FrameKind.FEEDBACK, NODE):
                    counts.append(protocol.decode_feedback(msg.data).counts)

        enable = protocol.ControlFrame(protocol.ControlRequest.ENABLE)
        send(FrameKind.CONTROL, protocol.encode_control(enable))
        for seq, code in enumerate(codes):
            send(FrameKind.COMMAND, protocol.encode_command(protocol.CommandFrame(code, seq % 128, True)))
    finally:
        host.shutdown()
        bus.shutdown()
    return truths, counts


def test_same_motion_as_the_native_drive_for_the_same_current() -> None:
    """Native with plant.input_delay_samples = 1 applies a command one period after the sample it
    answers; CiA 402 applies an RPDO at the SYNC after the TPDO it answers: the same timing, and
    1 DAC count = 1 per mille here (dac_lsb_A 0.5 mA, rated current 500 mA)."""
    config = make_config()
    assert config.plant.input_delay_samples == 1
    rng = random.Random(7)
    codes = [rng.randint(-1400, 1400) for _ in range(300)]
    native, native_counts = _native_truths(config, codes)
    with raw_rig(config) as rig:
        rig.enable()
        counts = []
        for k in range(len(codes) + 1):  # SYNC k, then the RPDO answering TPDO k
            frames = rig.sync()
            counts += [int.from_bytes(bytes(m.data)[2:6], "little", signed=True)
                       for m in frames if m.arbitration_id == TPDO1]  # fmt: skip
            if k < len(codes):
                rig.exchange(RPDO1, _rpdo(0x0F, codes[k]))
        ours = rig.truths
    n = len(native)
    assert n == len(codes) + 1 and len(ours) >= n
    for a, b in zip(native, ours[:n], strict=True):
        assert a.period_index == b.period_index and a.time_ns == b.time_ns
        assert a.applied_current_A == pytest.approx(b.applied_current_A, abs=1e-12)
        assert a.disturbance_A == pytest.approx(b.disturbance_A, abs=1e-12)
        assert a.state == pytest.approx(b.state, rel=1e-12, abs=1e-12)
    assert counts[:n] == native_counts
    assert max(abs(t.state[0]) for t in ours) > 1e-3  # it did move


def test_constant_torque_matches_the_exact_zoh_solution() -> None:
    config = make_config(sim={"disturbance": None})
    with raw_rig(config) as rig:
        rig.enable()
        rig.exchange(RPDO1, _rpdo(0x0F, 300))  # before SYNC 0: acts from t = 0
        for _ in range(51):
            rig.sync()
            rig.exchange(RPDO1, _rpdo(0x0F, 300))
        truth = rig.truths[50]
    current_A = 300 * 500e-6
    A, B = config.plant.A, config.plant.B
    t = 50 * config.plant.period_ns * 1e-9
    M = np.zeros((3, 3))
    M[:2, :2], M[:2, 2:] = A, B
    x = scipy.linalg.expm(M * t)[:2, 2] * current_A
    assert truth.time_ns == 50 * config.plant.period_ns and truth.applied_current_A == current_A
    assert truth.state == pytest.approx(tuple(x), rel=1e-9)


def test_one_period_input_delay_at_sync() -> None:
    config = make_config(sim={"disturbance": None})
    with raw_rig(config) as rig:
        rig.enable()
        rig.sync()  # SYNC 0
        rig.exchange(RPDO1, _rpdo(0x0F, 100))  # answers TPDO 0
        rig.sync()  # SYNC 1: integrates [t0, t1] with the old current, then applies 100
        rig.sync()  # SYNC 2
        currents = [t.applied_current_A for t in rig.truths]
        assert currents == [0.0, 0.0, pytest.approx(0.05)]  # acts from t1: seen at sample 2
        assert rig.truths[1].state == (0.0, 0.0)


def test_extra_plant_delay_beyond_the_protocol() -> None:
    config = make_config(
        sim={"disturbance": None},
        plant={"input_delay_samples": 2},
        **{"design.estimator": {"Lc": [0.75, 0.5, 0.0, 0.0]}, "design.feedback": {"Kc": [[1.0, 0, 0, 0]]}},
    )
    with raw_rig(config) as rig:
        rig.enable()
        rig.sync()
        rig.exchange(RPDO1, _rpdo(0x0F, 100))
        for _ in range(3):
            rig.sync()
        assert [t.applied_current_A for t in rig.truths] == [0.0, 0.0, 0.0, pytest.approx(0.05)]


def test_torque_quantization_clamp_and_statusword_limit_bit() -> None:
    with raw_rig(make_config(sim={"disturbance": None})) as rig:
        rig.write(0x6072, 0, 1000, 2)  # max torque 100 %
        rig.enable()
        rig.exchange(RPDO1, _rpdo(0x0F, -1500))
        rig.sync()  # applied (clamped) from here
        frames = rig.sync()
        tpdo = next(bytes(m.data) for m in frames if m.arbitration_id == TPDO1)
        assert int.from_bytes(tpdo[:2], "little") == 0x1A37  # + internal limit active (bit 11)
        assert rig.truths[-1].applied_current_A == pytest.approx(-0.5)
        assert rig.sdo(sdo_request(0x40, 0x6077, 0))[4:6] == (-1000).to_bytes(2, "little", signed=True)
        rig.write(0x6075, 0, 1000, 4)  # rated current 1 A: 1 per mille = 1 mA
        rig.exchange(RPDO1, _rpdo(0x0F, 123))
        rig.sync()
        rig.sync()
        assert rig.truths[-1].applied_current_A == pytest.approx(0.123)


def test_halt_and_mode_zero_command_no_torque() -> None:
    with raw_rig(make_config(sim={"disturbance": None})) as rig:
        rig.enable()
        rig.exchange(RPDO1, _rpdo(0x10F, 400))  # halt (bit 8)
        rig.sync()
        rig.sync()
        assert rig.truths[-1].applied_current_A == 0.0
        rig.exchange(RPDO1, _rpdo(0x0F, 400))
        rig.sync()
        rig.sync()
        assert rig.truths[-1].applied_current_A == pytest.approx(0.2)
        rig.write(0x6060, 0, 0, 1)  # no mode: the drive follows no torque
        rig.sync()
        assert rig.truths[-1].applied_current_A == 0.0
        statusword = int.from_bytes(rig.sdo(sdo_request(0x40, 0x6041, 0))[4:6], "little")
        assert statusword == 0x0237  # operation enabled, not following (bit 12 clear)


def test_disable_cuts_the_current_at_once() -> None:
    with raw_rig(make_config(sim={"disturbance": None})) as rig:
        rig.enable()
        rig.exchange(RPDO1, _rpdo(0x0F, 400))
        rig.sync()
        rig.write(0x6040, 0, 0x07, 2)  # disable operation by SDO between SYNCs
        rig.sync()
        assert rig.truths[-1].applied_current_A == 0.0


def test_velocity_actual_is_the_position_difference_per_second() -> None:
    with raw_rig(make_config(sim={"disturbance": None})) as rig:
        rig.enable()
        positions, velocities = [], []
        for _ in range(20):
            rig.exchange(RPDO1, _rpdo(0x0F, 500))
            for m in rig.sync():
                data = bytes(m.data)
                if m.arbitration_id == TPDO1:
                    positions.append(int.from_bytes(data[2:6], "little", signed=True))
                elif m.arbitration_id == 0x280 + NODE:  # TPDO2 default: statusword, velocity
                    velocities.append(int.from_bytes(data[2:6], "little", signed=True))
        period_s = 300e-6
        expected = [round((b - a) / period_s) for a, b in itertools.pairwise(positions)]
        assert velocities[1:] == expected and expected[-1] > 0
