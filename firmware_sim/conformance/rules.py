"""The rules of docs/PROTOCOL.md, checked from the host's side in one scripted session.

:func:`run_rules` drives a drive through listen, version check, enable, watchdog, fault, clear,
bad frame and stop, and returns one :class:`RuleResult` per rule of :data:`RULES` (the ids are
those of PROTOCOL.md's "Conformance" table). Checks that would command full current
(C1, C2) run only with ``full_current=True``: on a real drive the motor then moves.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, field

from dob_hil.link import protocol
from dob_hil.link.protocol import (
    DLC,
    HEARTBEAT_PERIOD_NS,
    MAX_PADDED_LEN,
    PROTOCOL_VERSION,
    ControlRequest,
    DriveState,
    FaultCode,
    FaultFrame,
    FeedbackFrame,
    FrameKind,
    HeartbeatFrame,
    Status,
)
from firmware_sim.conformance.probe import Probe, Rx

RULES: dict[str, str] = {
    "V1": "every HEARTBEAT carries protocol version 2",
    "V2": "a CONTROL of another protocol version is not acted on, and is answered by a HEARTBEAT",
    "F1": "every frame of the drive is its length (or padded up to 8 bytes) and decodes",
    "F2": "a CONTROL padded to 8 bytes is acted on",
    "H1": "a HEARTBEAT at least every 100 ms",
    "H2": "every CONTROL is answered by a HEARTBEAT of the resulting state",
    "S1": "FEEDBACK flows every period in every state (DISABLED, ENABLED, FAULT)",
    "S2": "the FEEDBACK sequence counts +1 per period (a restart is allowed on entering ENABLED)",
    "S3": "the FEEDBACK status agrees with the drive state",
    "E1": "CONTROL enable from DISABLED enables the drive",
    "E2": "CONTROL disable disables the drive",
    "W1": "the watchdog waits for the first valid COMMAND after enable",
    "W2": "a COMMAND answering every FEEDBACK keeps the drive enabled",
    "W3": "a COMMAND one period late is valid",
    "W4": "a duplicate COMMAND is stale: duplicates alone trip the watchdog",
    "W5": "a watchdog trip sends FAULT (WATCHDOG, info = periods), HEARTBEAT FAULT, status FAULT|WATCHDOG",
    "X1": "in FAULT, CONTROL enable is refused (HEARTBEAT FAULT)",
    "X2": "CLEAR_FAULT leads from FAULT to DISABLED",
    "X3": "a COMMAND shorter than 3 bytes faults BAD_FRAME, info = the id's low byte",
    "C1": "a COMMAND beyond the drive's limit is clamped: status SATURATED",
    "C2": "a COMMAND with Enable=0 stops (zero current), even when stale",
    "P1": "the host's stop sequence leaves the drive DISABLED, not in FAULT",
}

FULL_CURRENT_RULES = ("C1", "C2")
STOP_PERIODS_MAX = 10  # C2: a stop takes effect within this many periods (input delay included)
LISTEN_HEARTBEATS = 3  # H1: a listening window lasts until this many HEARTBEATs arrived
LISTEN_WINDOWS = 3  # H1 fails only if this many windows in a row show a gap over 200 ms
DUPLICATE_WATCHDOG_MAX = 60  # W4 by the watchdog needs duplicates not to alias (7-bit sequence)


@dataclass
class KitOptions:
    node_id: int = 1
    watchdog_periods: int = 10  # the drive's watchdog, as configured in the drive
    full_current: bool = False  # run C1/C2 (commands +32767 DAC counts for a few periods)
    answer_timeout_s: float = 0.5  # a HEARTBEAT answering a CONTROL must come within this
    step_timeout_s: float = 10.0  # wall-clock cap of any one step
    listen_s: float = 0.35  # the first, passive, observation


@dataclass
class RuleResult:
    rule: str
    title: str
    status: str  # "pass" | "fail" | "skip"
    detail: str = ""

    def to_dict(self) -> dict[str, str]:
        return {"rule": self.rule, "title": self.title, "status": self.status, "detail": self.detail}


@dataclass
class _Book:
    results: dict[str, RuleResult] = field(default_factory=dict)

    def record(self, rule: str, ok: bool, detail: str = "") -> bool:
        """Record a check of ``rule``; a rule fails if any of its checks fails (first failure kept)."""
        old = self.results.get(rule)
        if old is not None and old.status == "fail":
            return ok
        if ok and old is not None and old.status == "pass":
            return ok
        self.results[rule] = RuleResult(rule, RULES[rule], "pass" if ok else "fail", detail)
        return ok

    def skip(self, rule: str, why: str) -> None:
        self.results.setdefault(rule, RuleResult(rule, RULES[rule], "skip", why))


def _is_hb(state: DriveState | None = None) -> Callable[[Rx], bool]:
    def pred(rx: Rx) -> bool:
        return isinstance(rx.frame, HeartbeatFrame) and (state is None or rx.frame.state is state)

    return pred


def _is_fault(rx: Rx) -> bool:
    return isinstance(rx.frame, FaultFrame)


def _saturated(value: bool) -> Callable[[Rx], bool]:
    """FEEDBACK of an ENABLED drive with the SATURATED bit ``value``."""

    def pred(rx: Rx) -> bool:
        fb = rx.frame
        return (
            isinstance(fb, FeedbackFrame)
            and bool(fb.status & Status.ENABLED)
            and bool(fb.status & Status.SATURATED) is value
        )

    return pred


def _fault_text(rx: Rx | None) -> str:
    return "no FAULT" if rx is None else str(rx.frame)


def _hb_state(rx: Rx | None) -> str:
    if rx is None or not isinstance(rx.frame, HeartbeatFrame):
        return "no HEARTBEAT"
    return f"HEARTBEAT {rx.frame.state.name} (version {rx.frame.version})"


class _Session:
    def __init__(self, probe: Probe, opts: KitOptions) -> None:
        self.p = probe
        self.o = opts
        self.book = _Book()
        w = opts.watchdog_periods
        # beyond the watchdog, within the first-command allowance (at least 2 W periods, PROTOCOL.md)
        self.grace_periods = w + max(1, w // 2)
        self.run_periods = w + max(10, w // 2)

    # --- helpers ---------------------------------------------------------------------------------
    def control(self, request: ControlRequest, want: DriveState | None = None, **kw: object) -> Rx | None:
        """Send a CONTROL; the HEARTBEAT answering it: the first of state ``want``, or else the
        second HEARTBEAT after the request (a periodic one sent before the drive acted may come
        first), or else the last one within the answer timeout (None: no HEARTBEAT at all)."""
        mark = self.p.mark()
        self.p.control(request, **kw)  # type: ignore[arg-type]
        seen = [0]
        is_hb = _is_hb()

        def answer(rx: Rx) -> bool:
            if not is_hb(rx):
                return False
            seen[0] += 1
            return want is None or seen[0] >= 2 or rx.frame.state is want  # type: ignore[union-attr]

        rx = self.p.wait(mark, answer, periods=10**9, timeout_s=self.o.answer_timeout_s)
        if rx is None:
            heartbeats = self.p.since(mark, FrameKind.HEARTBEAT)
            rx = heartbeats[-1] if heartbeats else None
        self.book.record(
            "H2",
            rx is not None,
            "" if rx else f"no HEARTBEAT within {self.o.answer_timeout_s:g} s of CONTROL {request.name}",
        )
        return rx

    def state_after(self, request: ControlRequest, want: DriveState, **kw: object) -> tuple[bool, str]:
        rx = self.control(request, want, **kw)
        ok = rx is not None and isinstance(rx.frame, HeartbeatFrame) and rx.frame.state is want
        return ok, f"CONTROL {request.name} answered by {_hb_state(rx)}, expected {want.name}"

    def feedback_status(self, n: int) -> list[Status]:
        mark = self.p.mark()
        self.p.periods(n, self.o.step_timeout_s)
        return [
            rx.frame.status
            for rx in self.p.since(mark, FrameKind.FEEDBACK)
            if isinstance(rx.frame, FeedbackFrame)
        ]

    def faults_since(self, mark: int) -> list[FaultFrame]:
        return [rx.frame for rx in self.p.since(mark, FrameKind.FAULT) if isinstance(rx.frame, FaultFrame)]

    def to_disabled(self) -> bool:
        """Bring the drive to DISABLED (disable; clear a fault)."""
        for request in (ControlRequest.DISABLE, ControlRequest.CLEAR_FAULT):
            rx = self.control(request, DriveState.DISABLED)
            if (
                rx is not None
                and isinstance(rx.frame, HeartbeatFrame)
                and rx.frame.state is DriveState.DISABLED
            ):
                return True
        return False

    def enable(self) -> bool:
        ok, _ = self.state_after(ControlRequest.ENABLE, DriveState.ENABLED)
        return ok

    # --- the script ------------------------------------------------------------------------------
    def run(self) -> list[RuleResult]:
        self.listen()
        self.version()
        if self.enable_rules():
            self.watchdog_rules()
        self.fault_rules()
        self.bad_frame_rule()
        if self.o.full_current:
            self.current_rules()
        else:
            for rule in FULL_CURRENT_RULES:
                self.book.skip(rule, "commands full current: run with --full-current")
        self.stop_rule()
        self.frame_rules()
        return [self.book.results.get(r, RuleResult(r, RULES[r], "skip", "not reached")) for r in RULES]

    def listen(self) -> None:
        """H1 and S1 from passive observation.

        A window lasts at least ``listen_s`` and until three HEARTBEATs arrived (capped by
        ``step_timeout_s``). A host that stalls can stretch one window's gap without the drive
        being at fault, so H1 fails only when ``LISTEN_WINDOWS`` windows in a row all fail it.
        """
        heartbeats: list[Rx] = []
        feedback: list[Rx] = []
        verdict = (False, "not observed")
        for _ in range(LISTEN_WINDOWS):
            heartbeats, feedback = self._listen_window()
            verdict = self._heartbeat_verdict(heartbeats)
            if verdict[0] or len(heartbeats) < 2:  # silent for step_timeout_s: no retry
                break
        self.book.record("H1", *verdict)
        self.book.record(
            "S1",
            len(feedback) >= 3,
            f"{len(feedback)} FEEDBACK in the last window while {self.initial_state(heartbeats)}",
        )
        last = heartbeats[-1].frame if heartbeats else None
        if isinstance(last, HeartbeatFrame) and last.state is not DriveState.DISABLED:
            self.to_disabled()

    def _listen_window(self) -> tuple[list[Rx], list[Rx]]:
        p = self.p
        mark = p.mark()
        p.wait(mark, lambda rx: False, periods=10**9, timeout_s=self.o.listen_s)
        more = max(0.0, self.o.step_timeout_s - self.o.listen_s)
        if len(p.since(mark, FrameKind.HEARTBEAT)) < LISTEN_HEARTBEATS:
            counted = 0

            def enough(rx: Rx) -> bool:
                nonlocal counted
                counted += rx.kind is FrameKind.HEARTBEAT
                return counted >= LISTEN_HEARTBEATS

            p.wait(mark, enough, periods=10**9, timeout_s=more)
        return p.since(mark, FrameKind.HEARTBEAT), p.since(mark, FrameKind.FEEDBACK)

    def _heartbeat_verdict(self, heartbeats: list[Rx]) -> tuple[bool, str]:
        if len(heartbeats) < 2:
            return False, f"{len(heartbeats)} HEARTBEAT(s) in {self.o.step_timeout_s:g} s"
        worst = max(b.t_ns - a.t_ns for a, b in itertools.pairwise(heartbeats))
        return (
            worst <= 2 * HEARTBEAT_PERIOD_NS,
            f"largest gap {worst / 1e6:.1f} ms (allowed 200 ms: 100 ms + scheduling slack)",
        )

    @staticmethod
    def initial_state(heartbeats: list[Rx]) -> str:
        states = [rx.frame.state.name for rx in heartbeats if isinstance(rx.frame, HeartbeatFrame)]
        return states[-1] if states else "in an unknown state"

    def version(self) -> None:
        other = PROTOCOL_VERSION + 1
        rx = self.control(ControlRequest.ENABLE, version=other)
        answered = rx is not None and isinstance(rx.frame, HeartbeatFrame)
        acted = answered and rx.frame.state is DriveState.ENABLED  # type: ignore[union-attr]
        statuses = self.feedback_status(10)
        acted = acted or any(s & Status.ENABLED for s in statuses)
        self.book.record(
            "V2",
            answered and not acted,
            f"CONTROL ENABLE of version {other}: {_hb_state(rx)}; enabled: {acted}",
        )
        if acted:
            self.to_disabled()

    def enable_rules(self) -> bool:
        ok, text = self.state_after(ControlRequest.ENABLE, DriveState.ENABLED)
        self.book.record("E1", ok, text)
        if not ok:
            return False
        statuses = self.feedback_status(5)
        self.book.record(
            "S3",
            bool(statuses) and bool(statuses[-1] & Status.ENABLED) and not statuses[-1] & Status.FAULT,
            f"FEEDBACK status after enabling: {[int(s) for s in statuses[-3:]]}",
        )
        ok, text = self.state_after(ControlRequest.DISABLE, DriveState.DISABLED)
        self.book.record("E2", ok, text)
        statuses = self.feedback_status(5)
        self.book.record(
            "S3",
            bool(statuses) and not statuses[-1] & (Status.ENABLED | Status.FAULT),
            f"FEEDBACK status after disabling: {[int(s) for s in statuses[-3:]]}",
        )
        ok, text = self.state_after(
            ControlRequest.ENABLE, DriveState.ENABLED, pad=bytes([0xAA] * MAX_PADDED_LEN)
        )
        self.book.record("F2", ok, f"padded {text}")
        return ok or self.enable()

    def watchdog_rules(self) -> None:
        p, o, w = self.p, self.o, self.o.watchdog_periods
        mark = p.mark()
        p.periods(self.grace_periods, o.step_timeout_s)
        faults = self.faults_since(mark)
        self.book.record(
            "W1", not faults, f"{self.grace_periods} periods after enable without a COMMAND: faults {faults}"
        )
        if faults:
            self.to_disabled()
            if not self.enable():
                return
        for rule, mode in (("W2", "answer"), ("W3", "late")):
            mark = p.mark()
            p.set_mode(mode)
            n = p.periods(self.run_periods, o.step_timeout_s)
            faults = self.faults_since(mark)
            self.book.record(
                rule, not faults and n >= self.run_periods, f"{n} periods answered ({mode}): faults {faults}"
            )
            if faults:
                p.set_mode("off")
                self.to_disabled()
                if not self.enable():
                    return
        p.set_mode("answer")
        p.periods(3, o.step_timeout_s)
        mark = p.mark()
        # duplicates alone (every period the same, already answered sequence number) must trip the
        # watchdog; beyond 60 periods the 7-bit sequence wraps onto new feedback: silence instead
        by_duplicates = w <= DUPLICATE_WATCHDOG_MAX
        p.set_mode("repeat" if by_duplicates else "off")
        rx = p.wait(mark, _is_fault, periods=w + self.grace_periods, timeout_s=o.step_timeout_s)
        p.set_mode("off")
        if by_duplicates:
            n = len(p.since(mark, FrameKind.FEEDBACK))
            self.book.record("W4", rx is not None, f"duplicates for {n} periods: {_fault_text(rx)}")
        elif not o.full_current:
            self.book.skip(
                "W4", f"watchdog of {w} > {DUPLICATE_WATCHDOG_MAX} periods: run with --full-current"
            )
        expected = FaultFrame(FaultCode.WATCHDOG, min(w, 255))
        statuses = self.feedback_status(3)  # (and the HEARTBEAT that follows the FAULT arrives)
        after = p.since(rx.index + 1) if rx is not None else []
        hb_fault = any(
            isinstance(r.frame, HeartbeatFrame) and r.frame.state is DriveState.FAULT for r in after
        )
        status_ok = bool(statuses) and statuses[-1] == Status.FAULT | Status.WATCHDOG
        self.book.record(
            "W5",
            rx is not None and rx.frame == expected and hb_fault and status_ok,
            f"got {_fault_text(rx)} (expected {expected}), HEARTBEAT FAULT after it: {hb_fault}, "
            f"status {[int(s) for s in statuses]} (expected {int(Status.FAULT | Status.WATCHDOG)})",
        )
        if statuses:
            self.book.record("S1", True)

    def fault_rules(self) -> None:
        if not self._in_fault():
            self.p.send(self.p.command_id, b"\x00")  # a bad frame (X3) faults the drive in any state
            if not self._in_fault():
                self.book.skip("X1", "could not bring the drive into FAULT")
                self.book.skip("X2", "could not bring the drive into FAULT")
                return
        ok, text = self.state_after(ControlRequest.ENABLE, DriveState.FAULT)
        self.book.record("X1", ok, text)
        ok, text = self.state_after(ControlRequest.CLEAR_FAULT, DriveState.DISABLED)
        self.book.record("X2", ok, text)

    def _in_fault(self) -> bool:
        rx = self.control(ControlRequest.DISABLE)  # harmless in every state; answered with the state
        return rx is not None and isinstance(rx.frame, HeartbeatFrame) and rx.frame.state is DriveState.FAULT

    def bad_frame_rule(self) -> None:
        p = self.p
        if not self.enable():
            self.book.skip("X3", "the drive did not enable")
            return
        p.set_mode("answer")
        p.periods(5, self.o.step_timeout_s)
        p.set_mode("off")
        mark = p.mark()
        p.send(p.command_id, b"\x00\x00")  # 2 bytes
        rx = p.wait(
            mark, lambda r: isinstance(r.frame, FaultFrame), periods=50, timeout_s=self.o.step_timeout_s
        )
        expected = FaultFrame(FaultCode.BAD_FRAME, p.command_id & 0xFF)
        self.book.record(
            "X3",
            rx is not None and rx.frame == expected,
            f"got {rx.frame if rx else 'no FAULT'}, expected {expected}",
        )
        self.to_disabled()

    def current_rules(self) -> None:
        p, o = self.p, self.o
        if not self.enable():
            self.book.skip("C1", "the drive did not enable")
            self.book.skip("C2", "the drive did not enable")
            return
        p.set_mode("answer", current_counts=protocol.CURRENT_COUNTS_MAX)
        mark = p.mark()
        rx = p.wait(mark, _saturated(True), periods=20, timeout_s=o.step_timeout_s)
        self.book.record(
            "C1", rx is not None, "SATURATED seen" if rx else "no SATURATED status within 20 periods"
        )
        p.set_mode("off")
        last = p.last_answered if p.last_answered is not None else 0
        if o.watchdog_periods > DUPLICATE_WATCHDOG_MAX:  # W4 by the SATURATED status instead
            self.duplicate_by_saturation(last)
        mark = p.mark()
        p.command(0, last, False)  # a stop answering an already answered feedback: stale, still a stop
        window = STOP_PERIODS_MAX
        cleared = p.wait(mark, _saturated(False), periods=window, timeout_s=o.step_timeout_s)
        n = (
            len(p.since(mark, FrameKind.FEEDBACK))
            if cleared is None
            else sum(1 for r in p.since(mark, FrameKind.FEEDBACK) if r.index <= cleared.index)
        )
        self.book.record(
            "C2",
            cleared is not None,
            f"SATURATED {'cleared' if cleared else 'still set'} {n} period(s) after a stale Enable=0 "
            f"(allowed {window})",
        )
        self.to_disabled()

    def duplicate_by_saturation(self, last: int) -> None:
        """W4 without the watchdog: a duplicate of 0 A must not end the saturation."""
        p = self.p
        mark = p.mark()
        p.command(0, last, True)
        hold = max(1, min(5, self.o.watchdog_periods - 10))
        p.periods(hold, self.o.step_timeout_s)
        fbs = [r.frame for r in p.since(mark, FrameKind.FEEDBACK) if isinstance(r.frame, FeedbackFrame)]
        kept = bool(fbs) and all(fb.status & Status.SATURATED for fb in fbs)
        statuses = [int(fb.status) for fb in fbs]
        self.book.record("W4", kept, f"status after a duplicate of 0 A: {statuses} (SATURATED must stay)")

    def stop_rule(self) -> None:
        p = self.p
        if not self.enable():
            self.book.skip("P1", "the drive did not enable")
            return
        p.set_mode("answer")
        p.periods(10, self.o.step_timeout_s)
        p.set_mode("off")
        mark = p.mark()
        p.command(0, p.last_answered if p.last_answered is not None else 0, False)  # the stop COMMAND ...
        rx = self.control(ControlRequest.DISABLE)  # ... then CONTROL disable (as NativeDriveLink.safe_stop)
        p.periods(5, self.o.step_timeout_s)
        faults = self.faults_since(mark)
        ok = rx is not None and isinstance(rx.frame, HeartbeatFrame) and rx.frame.state is DriveState.DISABLED
        self.book.record("P1", ok and not faults, f"{_hb_state(rx)}; faults {faults}")

    def frame_rules(self) -> None:
        frames = self.p.since(0)
        bad = [rx for rx in frames if rx.frame is None or not DLC[rx.kind] <= len(rx.data) <= MAX_PADDED_LEN]
        self.book.record(
            "F1",
            not bad,
            f"{len(bad)} of {len(frames)} frames bad"
            + (f"; first: {bad[0].kind.name} {bad[0].data.hex()}: {bad[0].problem}" if bad else ""),
        )
        versions = {rx.frame.version for rx in frames if isinstance(rx.frame, HeartbeatFrame)}
        self.book.record("V1", versions == {PROTOCOL_VERSION}, f"versions seen: {sorted(versions)}")
        self.book.record("S2", *self._sequence(frames))

    @staticmethod
    def _sequence(frames: list[Rx]) -> tuple[bool, str]:
        """+1 per FEEDBACK; a jump is allowed at the first ENABLED feedback after the drive entered
        ENABLED (seen in the feedback status or in a HEARTBEAT since the previous feedback)."""
        prev: FeedbackFrame | None = None
        enabled = False  # the drive's last reported state was ENABLED
        entered = False  # it entered ENABLED since the previous feedback
        bad = 0
        first = ""
        for rx in frames:
            frame = rx.frame
            if isinstance(frame, HeartbeatFrame):
                now = frame.state is DriveState.ENABLED
                entered = entered or (now and not enabled)
                enabled = now
                continue
            if not isinstance(frame, FeedbackFrame):
                continue
            now = bool(frame.status & Status.ENABLED)
            entered = entered or (now and not enabled)
            if prev is not None:
                step = (frame.seq - prev.seq) % 256
                if not (entered and now) and not 1 <= step <= 8:  # up to 7 lost frames tolerated
                    bad += 1
                    first = first or f"{prev.seq} -> {frame.seq}"
            prev, enabled, entered = frame, now, False
        return bad == 0, f"{bad} sequence step(s) outside +1..+8" + (f"; first {first}" if first else "")


def run_rules(probe: Probe, opts: KitOptions) -> list[RuleResult]:
    """Run every rule against the drive behind ``probe`` (see the module docstring)."""
    return _Session(probe, opts).run()
