"""The drive-link seam: what the loop, the controller and the log see of a drive.

A profile (the native protocol today, CANopen CiA 402 cyclic synchronous torque next) implements
:class:`DriveLink` over a python-can bus. The loop never touches frames: it receives
:class:`Feedback`, asks the link to :meth:`~DriveLink.quantize` a current (the link knows its
DAC or torque resolution and clamps at the configured limit), and sends the resulting code.
Every raw frame the link sends or receives is handed to ``frame_hook`` for the log, and
everything unusual (faults, malformed or foreign frames, error frames) to ``event_hook``.
"""

from __future__ import annotations

import enum
import inspect
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final, NamedTuple, Protocol

import can

# can.Message's leading parameters, in this order: the per-period paths build their frames with
# positional arguments, ``can.Message(0.0, arbitration_id, False, False, False, None, None, data)``
# (keywords cost about 0.2 us more per frame). Checked here, at import, so that a python-can that
# reorders them fails loudly instead of building wrong frames.
MESSAGE_LEADING_PARAMS: Final = (
    "timestamp", "arbitration_id", "is_extended_id", "is_remote_frame", "is_error_frame", "channel",
    "dlc", "data",
)  # fmt: skip
if tuple(inspect.signature(can.Message.__init__).parameters)[1:9] != MESSAGE_LEADING_PARAMS:
    raise RuntimeError(
        f"python-can {can.__version__}: can.Message's leading parameters are no longer "
        f"{', '.join(MESSAGE_LEADING_PARAMS)}; dob_hil builds frames positionally (dob_hil.link.base)"
    )


class LinkEventKind(enum.Enum):
    DRIVE_FAULT = "drive_fault"  # the drive reported a fault
    DRIVE_STATE = "drive_state"  # the drive changed state (heartbeat)
    MALFORMED_FRAME = "malformed_frame"  # our id, but a payload that does not decode
    FOREIGN_FRAME = "foreign_frame"  # an id of no frame of ours, or another node's
    ERROR_FRAME = "error_frame"  # a CAN error frame
    STALE_FEEDBACK = "stale_feedback"  # duplicated or out-of-order feedback, discarded
    SEND_FAILED = "send_failed"  # bus.send raised
    ENCODER_JUMP = "encoder_jump"  # a counts step larger than the plausibility bound
    INVALID_COMMAND = "invalid_command"  # a non-finite current asked of quantize(): 0 A sent instead


@dataclass(frozen=True, slots=True)
class LinkEvent:
    time_ns: int
    kind: LinkEventKind
    message: str


class Feedback(NamedTuple):
    """One decoded, validated feedback sample from the drive (a NamedTuple: built every period,
    and a tuple is three times cheaper to construct than a frozen dataclass)."""

    rx_time_ns: int  # host receive time (time.monotonic_ns, or the bus timestamp in ns)
    seq: int  # the drive's sequence counter as sent
    raw_counts: tuple[int, ...]  # encoder counters as sent (wrapping), one per output
    counts: tuple[int, ...]  # unwrapped, continuous counts, one per output
    position: tuple[float, ...]  # counts / counts_per_unit, in the plant's output unit
    enabled: bool
    fault: bool
    saturated: bool  # the drive clamped the previous command


FrameHook = Callable[[can.Message, bool], None]  # (message, is_rx)
EventHook = Callable[[LinkEvent], None]


class DriveLink(Protocol):
    """One drive on one bus, as the loop sees it. Implementations: one per profile (``dob_hil.profiles``)."""

    @property
    def current_limit_A(self) -> float: ...

    def enable(self, timeout_ns: int) -> None:
        """Ask the drive to enable; raise :class:`~dob_hil.errors.DriveFault` if it does not."""

    def enable_lockstep(self, service: Callable[[], int], max_rounds: int = 3) -> None:
        """Enable against the embedded lockstep drive, which acts only when ``service()`` is
        called (in this thread); raise :class:`~dob_hil.errors.DriveFault` if it does not."""

    def receive_feedback(self, timeout_ns: int) -> Feedback | None:
        """The next valid feedback of our drive, or None after ``timeout_ns``.

        Frames that are not valid feedback of our node are reported to ``event_hook`` and
        skipped; they never reach the controller.
        """

    def quantize(self, current_A: tuple[float, ...]) -> tuple[tuple[int, ...], tuple[float, ...], bool]:
        """(codes, applied currents in A, saturated): clamp at the limit, round to the LSB."""

    def send_command(self, codes: tuple[int, ...], answers_seq: int) -> int:
        """Send one command; returns the send time in ns. Raises on a failed send."""

    def safe_stop(self) -> None:
        """Command zero current and disable the drive. Never raises; safe to call twice."""

    def close(self) -> None:
        """safe_stop() if needed, then release the bus. Safe to call twice."""
