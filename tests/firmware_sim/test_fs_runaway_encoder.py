"""The native lockstep fused period (LockstepClock._exchange) against the general path
(LockstepClock.fused = False) at a runaway position: a finite position whose count overflows is
an ENCODER fault (zero current, FAULT) on both, never an exception out of the drive."""

from __future__ import annotations

from collections import deque
from typing import Any

import can
from fs_support import make_config

from dob_hil.link.protocol import (
    CommandFrame,
    ControlFrame,
    ControlRequest,
    encode_command,
    encode_control,
)
from dob_hil.loop.inproc_bus import InProcessBus
from firmware_sim.lockstep import LockstepClock


def _enabled_clock(fused: bool, **config: Any) -> tuple[LockstepClock, deque[Any], deque[Any], list[Any]]:
    cfg = make_config(**config)
    truths: list[Any] = []
    to_drive: deque[Any] = deque()
    from_drive: deque[Any] = deque()
    clock = LockstepClock(InProcessBus("t", to_drive, from_drive), cfg, truths.append)
    clock.fused = fused
    enable = encode_control(ControlFrame(ControlRequest.ENABLE))
    to_drive.append(can.Message(arbitration_id=clock.core.control_id, data=enable, is_extended_id=False))
    clock.service()
    return clock, to_drive, from_drive, truths


def _command(clock: Any, to_drive: Any, code: int) -> str | None:
    """Answer the drive's last feedback with ``code`` and service it: the name of what it raised."""
    seq = clock.core.last_seq
    assert seq is not None
    payload = encode_command(CommandFrame(code, seq & 0x7F, True))
    to_drive.append(can.Message(arbitration_id=clock.core.command_id, data=payload, is_extended_id=False))
    try:
        clock.service()
    except Exception as exc:
        return type(exc).__name__
    return None


def _run(fused: bool, x: list[float]) -> tuple[Any, ...]:
    clock, to_drive, from_drive, _truths = _enabled_clock(fused)
    from_drive.clear()
    clock.core.plant._x = list(x)
    error = _command(clock, to_drive, 0)  # the fused path must not raise where the general path faults
    core = clock.core
    frames = [(m.arbitration_id, bytes(m.data)) for m in from_drive]
    clock.bus.shutdown()
    return error, core.state, core.time_ns, frames, vars(core.stats), core.path.held_A


def test_encoder_overflow_of_a_finite_position_faults_like_the_general_path() -> None:
    """A finite plant position whose counts overflow (position * counts_per_unit = inf) is an
    ENCODER fault on both paths (FAULT frame, FEEDBACK with the fault status, zero current,
    disabled). The fused _exchange once checked only the position for finiteness and let
    math.floor's OverflowError escape service() with the period half done."""
    x = [1.0e306, 0.0]
    general = _run(False, x)
    fused = _run(True, x)
    assert general[0] is None  # the general path handles it: an encoder fault
    assert fused == general


def _runaway(fused: bool) -> tuple[Any, ...]:
    """An unstable plant held at a constant command until its position runs away."""
    clock, to_drive, from_drive, truths = _enabled_clock(
        fused, plant={"A": [[1.0e4, 1.0], [0.0, 0.0]]}, sim={"disturbance": []}
    )
    error = None
    for _ in range(600):
        error = _command(clock, to_drive, 100)
        if error is not None:
            break
    core = clock.core
    frames = [(m.arbitration_id, bytes(m.data)) for m in from_drive]
    clock.bus.shutdown()
    return error, core.state, core.path.held_A, frames, vars(core.stats), len(truths)


def test_a_runaway_plant_faults_the_fused_drive_as_the_general_one() -> None:
    """A runaway (an unstable plant under a constant command): the position passes through the
    range where it is finite but its encoder counts overflow, and the drive takes an ENCODER fault
    (FAULT state, zero current, the later commands refused) on the fused path as on the general
    one. Before the fix the fused path let an OverflowError escape LockstepClock.service, ending
    the session with the drive still ENABLED at its commanded current."""
    general = _runaway(False)
    fused = _runaway(True)
    assert general[0] is None and general[2] == 0.0
    assert fused == general
