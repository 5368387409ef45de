"""NativeDriveLink against a scripted fake drive on python-can's virtual bus."""

from __future__ import annotations

import dataclasses
import math
import threading
from fractions import Fraction

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dob_hil.config import DriveConfig
from dob_hil.errors import ConfigError, DriveFault, ProtocolError
from dob_hil.link import protocol as p
from dob_hil.link.base import DriveLink, LinkEventKind
from dob_hil.link.native import NativeDriveLink, round_half_away
from dob_hil.link.protocol import (
    CommandFrame,
    ControlFrame,
    ControlRequest,
    DriveState,
    FaultCode,
    FrameKind,
    Status,
)
from dob_hil.link.unwrap import wrap_counts

from .conftest import Rig, make_rig, unique_channel

SECOND_NS = 1_000_000_000
LSB_A = 1.0 / 2048.0


def test_is_a_drive_link(rig: Rig) -> None:
    link: DriveLink = rig.link  # the Protocol is satisfied statically (mypy) and at run time
    assert link.current_limit_A == 0.7
    assert rig.link.limit_code == 1433
    assert rig.link.max_current_A == 1433 / 2048
    assert rig.link.n_axes == 1


# --- receiving ----------------------------------------------------------------------------------------
def test_feedback_is_decoded(rig: Rig) -> None:
    rig.drive.feedback(12345, 7, Status.ENABLED | Status.SATURATED)
    fb = rig.link.receive_feedback(SECOND_NS)
    assert fb is not None
    assert fb.seq == 7
    assert fb.raw_counts == (12345,)
    assert fb.counts == (12345,)
    assert fb.position == (12345 / 10000.0,)
    assert (fb.enabled, fb.fault, fb.saturated) == (True, False, True)
    assert fb.rx_time_ns == 1000  # the first clock reading, taken at receipt
    assert rig.link.last_seq == 7
    assert rig.link.stats.feedback == 1


def test_timeout_returns_none(rig: Rig) -> None:
    assert rig.link.receive_feedback(1_000_000) is None
    assert rig.link.receive_feedback(0) is None
    assert rig.rec.frames == []


def test_zero_timeout_reads_what_is_already_queued(rig: Rig) -> None:
    """Lockstep: the drive was serviced before receive(0); its heartbeat comes before the feedback."""
    rig.drive.heartbeat(DriveState.ENABLED)
    rig.drive.feedback(1, 0)
    fb = rig.link.receive_feedback(0)
    assert fb is not None and fb.seq == 0
    assert rig.link.drive_state is DriveState.ENABLED


@pytest.mark.parametrize("bits", [32, 16, 12])
@pytest.mark.parametrize("direction", [+1, -1])
def test_counts_are_unwrapped_across_the_rollover(
    bus_pair: tuple[can.BusABC, can.BusABC], bits: int, direction: int
) -> None:
    config = dataclasses.replace(DriveConfig(), encoder_bits=bits, encoder_counts_per_unit=4.0)
    rig = make_rig(*bus_pair, config=config)
    half = 2 ** (bits - 1)
    start = half - 250 if direction > 0 else -half + 250
    positions = [start + direction * 100 * k for k in range(6)]
    for seq, x in enumerate(positions):
        rig.drive.feedback(wrap_counts(x, bits), seq)
    got = [rig.link.receive_feedback(SECOND_NS) for _ in positions]
    assert [fb.counts[0] for fb in got if fb] == positions
    assert [fb.raw_counts[0] for fb in got if fb] == [wrap_counts(x, bits) for x in positions]
    assert [fb.position[0] for fb in got if fb] == [x / 4.0 for x in positions]
    assert rig.rec.kinds() == ["DRIVE_STATE"]  # unknown -> ENABLED; no ENCODER_JUMP, nothing stale


def test_foreign_malformed_and_error_frames_are_skipped_with_events(rig: Rig) -> None:
    d = rig.drive
    sent = [
        can.Message(arbitration_id=0x20000000, is_error_frame=True, data=bytes(8)),
        can.Message(arbitration_id=0x6B1, is_remote_frame=True, dlc=6),
        can.Message(arbitration_id=0x6B1, is_extended_id=True, data=bytes(6)),
        can.Message(arbitration_id=0x6B2, is_extended_id=False, data=bytes(6)),  # node 2's feedback
        can.Message(arbitration_id=0x100, is_extended_id=False, data=b"\x01"),  # no native frame
        can.Message(arbitration_id=0x6B1, is_extended_id=False, data=bytes(5)),  # short feedback
        can.Message(arbitration_id=0x6B1, is_extended_id=False, data=bytes(5) + b"\x10"),  # reserved bit
        can.Message(arbitration_id=0x6B1, is_extended_id=False, is_fd=True, data=bytes(6)),  # CAN FD
        can.Message(arbitration_id=0x681, is_extended_id=False, data=b"\x00\x00"),  # fault code 0
        can.Message(arbitration_id=0x6C1, is_extended_id=False, data=b"\x09\x02"),  # drive state 9
    ]
    for msg in sent:
        d.raw(msg)
    d.feedback(-5, 3)
    fb = rig.link.receive_feedback(SECOND_NS)
    assert fb is not None and fb.counts == (-5,) and fb.seq == 3
    assert rig.rec.kinds() == [
        "ERROR_FRAME",
        "FOREIGN_FRAME",
        "FOREIGN_FRAME",
        "FOREIGN_FRAME",
        "FOREIGN_FRAME",
        "MALFORMED_FRAME",
        "MALFORMED_FRAME",
        "MALFORMED_FRAME",
        "MALFORMED_FRAME",
        "MALFORMED_FRAME",
        "DRIVE_STATE",  # the valid feedback: unknown -> ENABLED
    ]
    texts = [ev.message for ev in rig.rec.events]
    assert "id 0x6B2" in texts[3] and "no frame of node 1" in texts[3]
    assert "expected 6 bytes (padding up to 8 allowed), got 5" in texts[5]
    assert "reserved status bits" in texts[6]
    assert "unknown fault code 0" in texts[8]
    assert "unknown drive state 9" in texts[9]
    # every received frame went to the frame hook first, as received
    assert len(rig.rec.frames) == len(sent) + 1
    assert all(is_rx for _, is_rx in rig.rec.frames)
    assert [m.arbitration_id for m, _ in rig.rec.frames] == [m.arbitration_id for m in sent] + [0x6B1]
    s = rig.link.stats
    assert (s.error_frames, s.foreign_frames, s.malformed_frames, s.feedback) == (1, 4, 5, 1)
    assert rig.link.last_fault is None and not rig.link.faulted


def test_own_command_and_control_echoes_are_skipped_silently(rig: Rig) -> None:
    """udp_multicast hands a process its own frames back: they must never look like anything."""
    rig.drive.send(FrameKind.COMMAND, p.encode_command(CommandFrame(100, 1, True)))
    rig.drive.send(FrameKind.CONTROL, p.encode_control(ControlFrame(ControlRequest.ENABLE)))
    assert rig.link.receive_feedback(0) is None
    assert rig.rec.events == []
    assert rig.link.stats.own_echoes == 2
    assert len(rig.rec.frames) == 2


def test_stale_and_duplicate_feedback_is_discarded(rig: Rig) -> None:
    for seq in (
        10,
        10,
        9,
        11,
        55,
        40,
        56,
        56 - 33,
    ):  # dup, 1 behind, next, ahead, behind, next, beyond window
        rig.drive.feedback(seq * 3, seq)
    got = []
    while (fb := rig.link.receive_feedback(0)) is not None:
        got.append(fb.seq)
    assert got == [10, 11, 55, 56, 23]  # 33 behind is outside the default window of 32: taken as ahead
    stale = [ev.message for ev in rig.rec.events if ev.kind is LinkEventKind.STALE_FEEDBACK]
    assert len(stale) == 3
    assert "seq 10 after 10 (duplicate)" in stale[0]
    assert "seq 9 after 10 (1 behind)" in stale[1]
    assert "seq 40 after 55 (15 behind)" in stale[2]
    assert rig.link.stats.stale_feedback == 3
    assert rig.link.stats.missed_feedback == (55 - 11 - 1) + (256 - 33 - 1)


def test_sequence_wraps_at_256(rig: Rig) -> None:
    for seq in (254, 255, 0, 1):
        rig.drive.feedback(seq, seq)
    got = [fb.seq for fb in iter(lambda: rig.link.receive_feedback(0), None) if fb]
    assert got == [254, 255, 0, 1]
    assert rig.link.stats.stale_feedback == 0


def test_fault_and_heartbeat_frames(rig: Rig) -> None:
    d = rig.drive
    d.heartbeat(DriveState.DISABLED)
    d.heartbeat(DriveState.DISABLED)  # no change: no event
    d.heartbeat(DriveState.ENABLED)
    d.fault(FaultCode.WATCHDOG, 10)
    d.feedback(0, 0, Status.FAULT | Status.WATCHDOG)
    fb = rig.link.receive_feedback(SECOND_NS)
    assert fb is not None and fb.fault and not fb.enabled
    assert rig.rec.kinds() == ["DRIVE_STATE", "DRIVE_STATE", "DRIVE_FAULT"]
    assert "unknown -> DISABLED (heartbeat)" in rig.rec.events[0].message
    assert "DISABLED -> ENABLED (heartbeat)" in rig.rec.events[1].message
    assert "WATCHDOG (info 10: periods without a valid command)" in rig.rec.events[2].message
    assert rig.link.faulted
    assert rig.link.last_fault == p.FaultFrame(FaultCode.WATCHDOG, 10)
    d.heartbeat(DriveState.DISABLED)  # fault cleared by the drive
    assert rig.link.receive_feedback(0) is None
    assert rig.link.drive_state is DriveState.DISABLED
    assert rig.link.last_fault is not None  # kept after the fault is cleared


@settings(max_examples=60, deadline=None)
@given(data=st.binary(min_size=0, max_size=8))
def test_any_payload_on_the_feedback_id_agrees_with_the_codec(data: bytes) -> None:
    channel = unique_channel()
    with (
        can.Bus(interface="virtual", channel=channel) as host,
        can.Bus(interface="virtual", channel=channel) as drive,
    ):
        rig = make_rig(host, drive)
        drive.send(can.Message(arbitration_id=0x6B1, is_extended_id=False, data=data))
        fb = rig.link.receive_feedback(0)
        try:
            frame = p.decode_feedback(data)
        except ProtocolError:
            assert fb is None
            assert rig.rec.kinds() == ["MALFORMED_FRAME"]
            return
        assert fb is not None
        assert (fb.raw_counts[0], fb.seq) == (frame.counts, frame.seq)
        assert (fb.enabled, fb.fault, fb.saturated) == (
            Status.ENABLED in frame.status,
            Status.FAULT in frame.status,
            Status.SATURATED in frame.status,
        )


# --- quantizing ------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("current_A", "code", "saturated"),
    [
        (0.0, 0, False),
        (0.5, 1024, False),
        (0.7, 1433, True),  # 1433.6 LSB: the limit is floor(0.7 * 2048) = 1433 codes
        (1433.4 * LSB_A, 1433, False),
        (1433.5 * LSB_A, 1433, True),  # rounds to 1434 > limit
        (-0.7, -1433, True),
        (5.0, 1433, True),
        (-1e300, -1433, True),
        (0.5 * LSB_A, 1, False),  # ties away from zero (Python's round would give 0)
        (-0.5 * LSB_A, -1, False),
        (2.5 * LSB_A, 3, False),  # (Python's round would give 2)
        (0.49999999999999994 * LSB_A, 0, False),  # the float just below a tie
    ],
)
def test_quantize(rig: Rig, current_A: float, code: int, saturated: bool) -> None:
    assert rig.link.quantize((current_A,)) == ((code,), (code * LSB_A,), saturated)
    assert rig.rec.events == []


def test_round_half_away_from_zero() -> None:
    assert [round_half_away(x) for x in (0.5, 1.5, 2.5, -0.5, -1.5, -2.5, 2.4999999999999996)] == [
        1,
        2,
        3,
        -1,
        -2,
        -3,
        2,
    ]


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_current_gives_zero_and_an_event(rig: Rig, bad: float) -> None:
    assert rig.link.quantize((bad,)) == ((0,), (0.0,), True)
    assert len(rig.rec.events) == 1
    assert "non-finite current" in rig.rec.events[0].message and "0 A commanded" in rig.rec.events[0].message
    assert rig.link.stats.nonfinite_currents == 1


def test_quantize_wants_one_axis(rig: Rig) -> None:
    with pytest.raises(ProtocolError, match="drives 1 axis, got 2"):
        rig.link.quantize((0.1, 0.2))


def reference_code(current_A: float, lsb_A: float, limit_A: float) -> tuple[int, bool]:
    """clamp(round_half_away(u / LSB), -floor(limit / LSB), +floor(limit / LSB)) in exact arithmetic."""
    limit = math.floor(Fraction(limit_A) / Fraction(lsb_A))
    quotient = current_A / lsb_A  # the float quotient the spec names, then exact rounding
    if math.isinf(quotient):
        return (limit if quotient > 0 else -limit), True
    x = Fraction(quotient)
    q = math.floor(abs(x) + Fraction(1, 2)) * (1 if x >= 0 else -1)
    return max(-limit, min(limit, q)), abs(q) > limit


@given(
    current_A=st.floats(allow_nan=False, allow_infinity=False),
    lsb_A=st.sampled_from([1.0 / 2048.0, 1e-3, 1.0 / 4096.0, 0.01]),
    limit_A=st.sampled_from([0.7, 1.0, 3.3]),
)
def test_quantize_property(current_A: float, lsb_A: float, limit_A: float) -> None:
    config = dataclasses.replace(DriveConfig(), dac_lsb_A=lsb_A, current_limit_A=limit_A)
    link = NativeDriveLink(can.Bus(interface="virtual", channel=unique_channel()), config, owns_bus=True)
    try:
        (code,), (applied,), saturated = link.quantize((current_A,))
    finally:
        link.close()
    assert (code, saturated) == reference_code(current_A, lsb_A, limit_A)
    assert applied == code * lsb_A
    assert abs(applied) <= limit_A
    if not saturated:
        assert abs(applied - current_A) <= lsb_A / 2 * (1 + 1e-12)


# --- sending ---------------------------------------------------------------------------------------------
def test_send_command(rig: Rig) -> None:
    t_ns = rig.link.send_command((1433,), 300)
    assert t_ns == rig.clock.now_ns
    rig.link.request_enable()
    rig.link.send_command((-7,), 127)
    assert rig.drive.received() == [
        (1, CommandFrame(1433, 300 % 128, False)),
        (1, ControlFrame(ControlRequest.ENABLE)),
        (1, CommandFrame(-7, 127, True)),
    ]
    tx = [(m.arbitration_id, bytes(m.data), is_rx) for m, is_rx in rig.rec.frames]
    assert tx == [
        (0x6A1, bytes.fromhex("99052c"), False),
        (0x691, b"\x01\x02", False),
        (0x6A1, bytes.fromhex("f9ffff"), False),
    ]
    assert rig.link.stats.tx_frames == 3


@pytest.mark.parametrize(("code", "sent"), [(5000, 1433), (-32768, -1433), (1434, 1433)])
def test_send_command_never_exceeds_the_limit_code(rig: Rig, code: int, sent: int) -> None:
    rig.link.send_command((code,), 0)
    assert rig.drive.received() == [(1, CommandFrame(sent, 0, False))]
    assert rig.link.stats.clamped_commands == 1


def test_send_command_refuses_non_integers(rig: Rig) -> None:
    with pytest.raises(ProtocolError, match="expected integer current_counts"):
        rig.link.send_command((1.5,), 0)  # type: ignore[arg-type]
    assert rig.drive.received() == []


def test_send_failure_is_reported_and_raised_as_drive_fault(
    rig: Rig, monkeypatch: pytest.MonkeyPatch
) -> None:
    def failing_send(msg: can.Message, timeout: float | None = None) -> None:
        raise can.CanOperationError("Transmit buffer full")

    monkeypatch.setattr(rig.host, "send", failing_send)
    with pytest.raises(
        DriveFault, match=r"node 1: sending COMMAND \(id 0x6A1\) failed: Transmit buffer full"
    ) as info:
        rig.link.send_command((10,), 1)
    assert isinstance(info.value.__cause__, can.CanOperationError)
    assert rig.rec.kinds() == ["SEND_FAILED"]
    assert rig.rec.frames == []  # nothing was sent, nothing is logged as sent
    assert rig.link.stats.send_failures == 1


# --- enable, stop, close ------------------------------------------------------------------------------------
def test_lockstep_enable(rig: Rig) -> None:
    rig.link.request_enable()
    assert rig.link.poll_enabled() is False
    assert rig.drive.received() == [(1, ControlFrame(ControlRequest.ENABLE))]
    rig.drive.heartbeat(DriveState.ENABLED)  # "service" the drive
    rig.link.wait_enabled(0)
    assert rig.link.drive_state is DriveState.ENABLED
    assert rig.link.enable_requested


def test_poll_enabled_sees_feedback_status(rig: Rig) -> None:
    rig.drive.heartbeat(DriveState.ENABLED)  # stale state from before the request
    assert rig.link.receive_feedback(0) is None
    rig.link.request_enable()
    rig.drive.feedback(0, 0, Status.ENABLED)
    assert rig.link.poll_enabled() is True


def test_enable_against_a_drive_thread(rig: Rig) -> None:
    def drive_side() -> None:
        msg = rig.drive.bus.recv(5.0)
        if msg is not None and p.decode(msg.arbitration_id, msg.data)[1] == ControlFrame(
            ControlRequest.ENABLE
        ):
            rig.drive.heartbeat(DriveState.ENABLED)

    thread = threading.Thread(target=drive_side)
    thread.start()
    rig.link.enable(5 * SECOND_NS)
    thread.join()
    assert rig.link.drive_state is DriveState.ENABLED


def test_enable_timeout_names_the_last_state(rig: Rig) -> None:
    rig.drive.heartbeat(DriveState.FAULT)
    with pytest.raises(
        DriveFault,
        match=r"did not report enabled within 1 ms \(last reported state: FAULT; fault code unknown",
    ) as info:
        rig.link.enable(1_000_000)
    assert "--clear-fault" in str(info.value)
    assert not rig.link.enable_requested


def test_enable_of_a_faulted_drive_names_code_info_rejections_and_remedy(rig: Rig) -> None:
    """A drive left in FAULT (say, by a killed host) refuses to enable: the error says why."""
    rig.drive.fault(FaultCode.WATCHDOG, 10)
    rig.drive.raw(can.Message(arbitration_id=0x6B1, is_extended_id=False, data=bytes(5)))  # short
    rig.drive.feedback(0, 7, Status.FAULT | Status.WATCHDOG)
    assert rig.link.receive_feedback(0) is not None
    rig.link.request_enable()
    rig.drive.heartbeat(DriveState.FAULT)  # the drive's answer: enable refused
    with pytest.raises(DriveFault) as info:
        rig.link.poll_enabled()
    text = str(info.value)
    assert "the drive refuses to enable: the drive is in FAULT (last fault WATCHDOG (info 10" in text
    assert (
        "rejected 1 frame(s) of node 1 (1 malformed, 0 stale, 0 undeliverable; first: id 0x6B1 DLC 5" in text
    )
    assert "dob-hil run --clear-fault" in text


def test_clear_fault_waits_until_the_drive_leaves_fault(rig: Rig) -> None:
    rig.drive.fault(FaultCode.WATCHDOG, 10)
    assert rig.link.receive_feedback(0) is None and rig.link.faulted

    def drive_side() -> None:
        msg = rig.drive.bus.recv(5.0)
        if msg is not None and p.decode(msg.arbitration_id, msg.data)[1] == ControlFrame(
            ControlRequest.CLEAR_FAULT
        ):
            rig.drive.heartbeat(DriveState.DISABLED)

    thread = threading.Thread(target=drive_side)
    thread.start()
    rig.link.clear_fault(5 * SECOND_NS)
    thread.join()
    assert rig.link.drive_state is DriveState.DISABLED


def test_clear_fault_of_a_drive_that_stays_faulted_names_the_fault(rig: Rig) -> None:
    rig.drive.fault(FaultCode.ENCODER)
    with pytest.raises(DriveFault, match=r"did not leave FAULT within 1 ms of ClearFault .*ENCODER"):
        rig.link.clear_fault(1_000_000)


def test_a_heartbeat_of_another_version_is_refused_naming_both(rig: Rig) -> None:
    rig.link.request_enable()
    rig.drive.send(FrameKind.HEARTBEAT, p.encode_heartbeat(p.HeartbeatFrame(DriveState.ENABLED, 3)))
    with pytest.raises(DriveFault, match="native protocol version 3, this host version 2"):
        rig.link.poll_enabled()
    assert rig.link.drive_state is None  # nothing of that heartbeat was believed
    assert rig.link.stats.version_mismatches == 1


def test_a_version_1_drive_is_named_when_enabling_fails(rig: Rig) -> None:
    rig.drive.raw(can.Message(arbitration_id=0x701, is_extended_id=False, data=b"\x00"))
    with pytest.raises(DriveFault, match=r"at 0x701 that look like a native protocol version 1 heartbeat"):
        rig.link.enable(1_000_000)


def test_feedback_sequence_restarting_on_enable_is_accepted(rig: Rig) -> None:
    """A drive may restart its sequence when it enters ENABLED: no feedback is discarded."""
    for seq in range(10, 20):
        rig.drive.feedback(0, seq, Status(0))  # disabled: feedback flows, sequence 10..19
    while rig.link.receive_feedback(0) is not None:
        pass
    rig.link.request_enable()
    for seq in range(5):
        rig.drive.feedback(seq, seq, Status.ENABLED)  # restarted at 0
    got = [fb.seq for fb in iter(lambda: rig.link.receive_feedback(0), None) if fb]
    assert got == [0, 1, 2, 3, 4]
    assert rig.link.stats.stale_feedback == 0 and rig.link.stats.sequence_restarts == 1


@pytest.mark.parametrize("padding", [b"\x00\x00", b"\xaa\xaa", b"\xff\xff"])
def test_frames_padded_to_8_bytes_are_accepted(rig: Rig, padding: bytes) -> None:
    rig.drive.send(FrameKind.HEARTBEAT, b"\x01\x02" + padding * 3)
    rig.drive.send(FrameKind.FEEDBACK, p.encode_feedback(p.FeedbackFrame(-9, 4, Status.ENABLED)) + padding)
    fb = rig.link.receive_feedback(0)
    assert fb is not None and fb.counts == (-9,) and fb.seq == 4
    assert rig.link.stats.malformed_frames == 0 and rig.link.drive_state is DriveState.ENABLED


def test_a_frame_the_bus_cannot_deliver_is_an_event_not_an_end(
    rig: Rig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """udp_multicast raises CanOperationError for a datagram that is not a frame: skip it."""
    real_recv = rig.host.recv
    calls = iter([True, False])

    def recv(timeout: float | None = None) -> can.Message | None:
        if next(calls, False):
            raise can.CanOperationError("could not unpack received message")
        return real_recv(timeout)

    monkeypatch.setattr(rig.host, "recv", recv)
    rig.drive.feedback(3, 1)
    fb = rig.link.receive_feedback(SECOND_NS)
    assert fb is not None and fb.seq == 1
    assert rig.rec.kinds()[0] == "MALFORMED_FRAME" and "could not unpack" in rig.rec.events[0].message
    assert rig.link.stats.rx_errors == 1


def test_a_broken_bus_still_ends_the_run(rig: Rig, monkeypatch: pytest.MonkeyPatch) -> None:
    def recv(timeout: float | None = None) -> can.Message | None:
        raise can.CanOperationError("network down")

    monkeypatch.setattr(rig.host, "recv", recv)
    with pytest.raises(DriveFault, match="failed 1000 times in a row: network down"):
        rig.link.receive_feedback(SECOND_NS)


def test_fault_while_enabling_raises(rig: Rig) -> None:
    rig.link.request_enable()
    rig.drive.fault(FaultCode.ENCODER)
    with pytest.raises(DriveFault, match="faulted while enabling: ENCODER"):
        rig.link.poll_enabled()
    with pytest.raises(DriveFault, match="no enable attempt in progress"):
        rig.link.wait_enabled(0)


def test_safe_stop_sends_one_stop_answering_the_newest_feedback(rig: Rig) -> None:
    """Byte for byte: a zero COMMAND with the enable bit clear answering the newest feedback
    (queued, not yet read: so the drive takes it as valid), then CONTROL disable; once."""
    rig.drive.feedback(0, 77)
    assert rig.link.receive_feedback(0) is not None
    rig.link.request_enable()
    rig.link.send_command((5,), 77)  # the loop answered 77 ...
    rig.drive.feedback(0, 78)  # ... and 78 is queued, unread, when the stop comes
    rig.link.safe_stop()
    rig.link.safe_stop()  # one stop sequence: the second call sends nothing
    rig.link.close()  # nor does close
    sent = [(m.arbitration_id, bytes(m.data)) for m, is_rx in rig.rec.frames if not is_rx]
    assert sent == [
        (0x691, bytes.fromhex("0102")),  # CONTROL enable, version 2
        (0x6A1, bytes.fromhex("0500cd")),  # 5 counts answering 77 (0x4D), enable bit set: 0xCD
        (0x6A1, bytes.fromhex("00004e")),  # stop: 0 counts answering 78 (0x4E), enable bit clear
        (0x691, bytes.fromhex("0002")),  # CONTROL disable, version 2
    ]
    assert not rig.link.enable_requested


def test_safe_stop_sends_no_command_to_a_drive_not_known_enabled(rig: Rig) -> None:
    """A drive may fault on a COMMAND while DISABLED: the stop of a drive that never reported
    ENABLED is CONTROL disable alone; after the next enable request a stop goes out again."""
    rig.drive.feedback(0, 3, Status(0))
    assert rig.link.receive_feedback(0) is not None
    rig.link.safe_stop()
    rig.link.request_enable()
    rig.link.safe_stop()
    assert rig.drive.received() == [
        (1, ControlFrame(ControlRequest.DISABLE)),
        (1, ControlFrame(ControlRequest.ENABLE)),
        (1, ControlFrame(ControlRequest.DISABLE)),
    ]


def test_safe_stop_never_raises(rig: Rig, monkeypatch: pytest.MonkeyPatch) -> None:
    def failing_send(msg: can.Message, timeout: float | None = None) -> None:
        raise can.CanOperationError("bus off")

    rig.drive.feedback(0, 0, Status.ENABLED)
    assert rig.link.receive_feedback(0) is not None
    rig.rec.events.clear()
    monkeypatch.setattr(rig.host, "send", failing_send)
    rig.link.safe_stop()
    assert rig.rec.kinds() == ["SEND_FAILED", "SEND_FAILED"]  # both frames were tried
    rig.link.safe_stop()  # a stop that did not go out is tried again
    assert rig.rec.kinds() == ["SEND_FAILED"] * 4

    def exploding_hook(ev: object) -> None:
        raise RuntimeError("logger is gone")

    link = NativeDriveLink(rig.host, DriveConfig(), event_hook=exploding_hook)
    link.safe_stop()  # still does not raise: the failure goes to the Python log
    link.close()


def test_close_stops_once_and_shuts_down_an_owned_bus(bus_pair: tuple[can.BusABC, can.BusABC]) -> None:
    host, drive_bus = bus_pair
    rig = make_rig(host, drive_bus, owns_bus=True)
    shutdowns: list[int] = []
    real_shutdown = host.shutdown

    def counting_shutdown() -> None:
        shutdowns.append(1)
        real_shutdown()

    host.shutdown = counting_shutdown  # type: ignore[method-assign]
    with rig.link:
        pass
    rig.link.close()
    rig.link.safe_stop()  # after close: nothing
    assert rig.drive.received() == [(1, ControlFrame(ControlRequest.DISABLE))]  # never enabled: no COMMAND
    assert shutdowns == [1]
    assert rig.link.closed
    with pytest.raises(DriveFault, match="closed"):
        rig.link.receive_feedback(0)


def test_close_leaves_a_borrowed_bus_open(rig: Rig) -> None:
    rig.link.close()
    rig.drive.feedback(0, 0)
    assert rig.host.recv(1.0) is not None


def test_hooks_see_every_frame_in_a_cycle(rig: Rig) -> None:
    rig.link.request_enable()
    rig.drive.heartbeat(DriveState.ENABLED)
    rig.link.wait_enabled(0)
    for k in range(5):
        rig.drive.feedback(k * 10, k)
        fb = rig.link.receive_feedback(SECOND_NS)
        assert fb is not None
        codes, _, _ = rig.link.quantize((0.01 * k,))
        rig.link.send_command(codes, fb.seq)
    rig.link.close()
    directions = [(m.arbitration_id, is_rx) for m, is_rx in rig.rec.frames]
    cycle = [(0x6B1, True), (0x6A1, False)]
    assert directions == [(0x691, False), (0x6C1, True), *(cycle * 5), (0x6A1, False), (0x691, False)]


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"profile": "cia402"}, "drive.profile"),
        ({"current_limit_A": 0.0001}, "drive.current_limit_A"),
        ({"current_limit_A": 100.0}, "drive.current_limit_A"),
        ({"node_id": 200}, "drive.node_id"),
        ({"node_id": 16}, "drive.node_id"),
        ({"encoder_bits": 70}, "drive.encoder_bits"),
    ],
)
def test_bad_drive_config_is_refused(change: dict[str, object], field: str) -> None:
    config = dataclasses.replace(DriveConfig(), **change)  # type: ignore[arg-type]
    with can.Bus(interface="virtual", channel=unique_channel()) as bus, pytest.raises(ConfigError) as info:
        NativeDriveLink(bus, config)
    assert info.value.field == field


def test_sequence_restart_after_a_quick_disable_and_enable_is_accepted(rig: Rig) -> None:
    """Disabled and enabled again within one period: no DISABLED feedback in between, only the
    heartbeats; the restarted sequence is still accepted."""
    rig.link.request_enable()
    rig.drive.heartbeat(DriveState.ENABLED)
    for seq in (40, 41, 42):
        rig.drive.feedback(0, seq, Status.ENABLED)
    rig.drive.heartbeat(DriveState.DISABLED)
    rig.drive.heartbeat(DriveState.ENABLED)
    rig.drive.feedback(0, 0, Status.ENABLED)
    rig.drive.feedback(0, 1, Status.ENABLED)
    got = [fb.seq for fb in iter(lambda: rig.link.receive_feedback(0), None) if fb]
    assert got == [40, 41, 42, 0, 1]
    assert rig.link.stats.stale_feedback == 0
