"""The injectors themselves: FaultyBus (seeded, deterministic, each fault as documented) and the
drive's [sim.faults] (period index from the first enable, encoder jump wrapped)."""

from __future__ import annotations

import can
import pytest
from fault_support import config_text

from dob_hil.config import FaultsConfig, parse_config_text
from firmware_sim.faults import DriveFaults, period_of
from firmware_sim.faulty_bus import FaultPlan, FaultyBus


def _feed(plan: FaultPlan, n: int = 200) -> tuple[list[tuple[int, bytes]], FaultyBus]:
    channel = f"faulty-{id(plan)}"
    src = can.Bus(interface="virtual", channel=channel)
    bus = FaultyBus(can.Bus(interface="virtual", channel=channel), plan)
    try:
        for i in range(n):
            src.send(
                can.Message(
                    arbitration_id=0x181, data=bytes([i % 256, 0, 0, 0, i % 256, 1]), is_extended_id=False
                )
            )
        out = []
        while (msg := bus.recv(0)) is not None:
            out.append((msg.arbitration_id, bytes(msg.data)))
        return out, bus
    finally:
        src.shutdown()
        bus.shutdown()


def test_faulty_bus_is_deterministic_and_does_what_it_records() -> None:
    plan = FaultPlan(
        seed=3, drop_probability=0.1, duplicate_probability=0.05, delay_probability=0.05, delay_frames=2
    )
    a, bus_a = _feed(plan)
    b, bus_b = _feed(plan)
    assert a == b and bus_a.record == bus_b.record
    counts = bus_a.counts()
    assert counts["drop"] > 0 and counts["duplicate"] > 0 and counts["delay"] > 0
    # every frame arrives once, plus its duplicate, minus the dropped ones (delayed ones at the end
    # may still be held)
    assert len(a) <= 200 - counts["drop"] + counts["duplicate"]
    first_bytes = [d[0] for _, d in a]
    dropped = {i for kind, i, _ in bus_a.record if kind == "drop"}
    assert not dropped & set(first_bytes)
    # a frame delayed by 2 comes right after the second frame delivered after it
    delayed = next(i for kind, i, _ in bus_a.record if kind == "delay")
    pos = first_bytes.index(delayed)
    assert first_bytes[pos - 1] > delayed


def test_faulty_bus_corrupts_changes_dlc_and_injects() -> None:
    inject = (can.Message(arbitration_id=0x7FF, data=b"\x01", is_extended_id=False),)
    out, _ = _feed(
        FaultPlan(corrupt_probability=1.0, corrupt_xor=b"\xff", inject_every=10, inject=inject), 20
    )
    assert all(d == bytes(x ^ 0xFF for x in bytes([i % 256, 0, 0, 0, i % 256, 1])) for i, (_, d) in
               enumerate(o for o in out if o[0] == 0x181))  # fmt: skip
    assert sum(aid == 0x7FF for aid, _ in out) == 2
    out, _ = _feed(FaultPlan(dlc_probability=1.0), 20)
    assert all(len(d) != 6 for _, d in out)


def test_faulty_bus_send_failures_and_silent_drops() -> None:
    channel = "faulty-send"
    sink = can.Bus(interface="virtual", channel=channel)
    bus = FaultyBus(
        can.Bus(interface="virtual", channel=channel),
        FaultPlan(tx_match=0x201, send_fail_at=2, send_fail_count=2),
    )
    try:
        msg = can.Message(arbitration_id=0x201, data=b"\0\0\0", is_extended_id=False)
        other = can.Message(arbitration_id=0x601, data=b"\0", is_extended_id=False)
        bus.send(msg)
        bus.send(other)  # not counted by tx_match
        bus.send(msg)
        with pytest.raises(can.CanOperationError, match="buffer full"):
            bus.send(msg)  # the 3rd COMMAND (index 2) fails
        with pytest.raises(can.CanOperationError):
            bus.send(other)  # and the next send of any id: 2 in the window
        bus.send(msg)
        received = []
        while (m := sink.recv(0)) is not None:
            received.append(m.arbitration_id)
        assert received == [0x201, 0x601, 0x201, 0x201]
    finally:
        sink.shutdown()
        bus.shutdown()
    with pytest.raises(ValueError):
        FaultPlan(drop_probability=1.5)


def test_drive_faults_from_config() -> None:
    jump = {"encoder_jump_at_s": 0.0003, "encoder_jump_counts": 40000}
    cfg = parse_config_text(config_text(drive={"encoder_bits": 16}, faults=jump))
    faults = DriveFaults.from_config(cfg)
    assert faults is not None and faults.jump_period == 1
    assert faults.counts(5, 100) == 100  # before the first enable nothing happens
    faults.on_enabled(10)
    faults.on_enabled(50)  # only the first enable counts
    assert faults.counts(10, 100) == 100
    assert faults.counts(11, 30000) == (30000 + 40000 + 2**15) % 2**16 - 2**15  # wrapped to 16 bits
    assert DriveFaults.from_config(parse_config_text(config_text())) is None
    assert (
        period_of(None, 300_000) is None and period_of(1e-9, 300_000) == 1 and period_of(0.3, 300_000) == 1000
    )
    assert not FaultsConfig().active and FaultsConfig(silent_at_s=1.0).active
