"""Prints the measured fault cases at the end of a run without xdist (``pytest tests/faults -p no:xdist``)."""

from __future__ import annotations

from typing import Any

from fault_support import RESULTS


def pytest_terminal_summary(terminalreporter: Any) -> None:
    if not RESULTS:
        return
    tr = terminalreporter
    tr.section("fault cases measured")
    tr.write_line(
        "| case | exit reason | samples | missing | max run | max code | trip periods | rms | ended "
        "| injected | events |"
    )
    for m in RESULTS:
        tr.write_line(m.row())
