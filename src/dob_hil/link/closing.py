"""What every link does to stop and close, whatever its profile: run each step of its stop
sequence so that one failed step never keeps the next from running (a failure is reported as a
SEND_FAILED event, never raised), close once (stop, then shut the bus down if the link owns it),
refuse to act once closed, and close on leaving a ``with`` block."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TypeVar

import can

from dob_hil.errors import DriveFault
from dob_hil.link.base import LinkEventKind

_log = logging.getLogger(__name__)
_L = TypeVar("_L", bound="ClosingLink")


class ClosingLink:
    """Base of the profiles' links. Subclasses set ``_bus``, ``_owns_bus``, ``_node``,
    ``_clock_ns`` and ``_closed = False``, and implement :meth:`safe_stop` and :meth:`_event`."""

    _bus: can.BusABC
    _owns_bus: bool
    _node: int
    _closed: bool
    _clock_ns: Callable[[], int]

    def safe_stop(self) -> None:
        raise NotImplementedError

    def _event(self, time_ns: int, kind: LinkEventKind, message: str) -> None:
        raise NotImplementedError

    def _stop_step(self, what: str, step: Callable[[], None], raise_errors: bool = False) -> bool:
        """Run one step of the stop sequence; True if it succeeded."""
        try:
            step()
            return True
        except DriveFault:
            if raise_errors:
                raise
            return False  # _send reported SEND_FAILED already (or the bus is broken)
        except Exception as exc:
            if raise_errors:
                raise
            try:
                self._event(
                    self._clock_ns(),
                    LinkEventKind.SEND_FAILED,
                    f"node {self._node}: safe_stop: {what} failed: {exc!r}",
                )
            except Exception:
                _log.exception("safe_stop of node %d: %s failed and event_hook raised", self._node, what)
            return False

    def close(self) -> None:
        """safe_stop() once, then shut the bus down if this link owns it. Safe to call twice."""
        if self._closed:
            return
        try:
            self.safe_stop()
        finally:
            self._closed = True
            if self._owns_bus:
                try:
                    self._bus.shutdown()
                except Exception:
                    _log.exception("shutting down the CAN bus of node %d failed", self._node)

    def _check_open(self) -> None:
        if self._closed:
            raise DriveFault(f"node {self._node}: the drive link is closed")

    def __enter__(self: _L) -> _L:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
