"""Conformance kit for drive implementers: the host's side of every rule of docs/PROTOCOL.md.

Run it against any drive on any python-can bus (the drive must be powered, DISABLED or in FAULT,
and nothing else may command it meanwhile)::

    python -m firmware_sim.conformance -i socketcan -c can0 --node 1 --watchdog-periods 10
    python -m firmware_sim.conformance -i udp_multicast -c 239.74.163.9 --node 3 --json

It prints pass, fail or skip per rule (``--json``: a JSON document) and exits 0 when no rule
failed, 1 when one did, 2 for bad arguments or a bus that cannot be opened. The drive is left
DISABLED. ``--full-current`` adds the two rules that command the drive's full current for a few
periods (C1, C2): a motor connected to a real drive then moves.

:func:`run_conformance` is the same from Python (firmware_sim's tests run it against the simulated
drive and its variants, :mod:`firmware_sim.behaviour`).
"""

from __future__ import annotations

import can

from firmware_sim.conformance.probe import Probe
from firmware_sim.conformance.rules import RULES, KitOptions, RuleResult, run_rules


def run_conformance(bus: can.BusABC, options: KitOptions) -> list[RuleResult]:
    """Every rule of :data:`RULES` against the drive of ``options.node_id`` on ``bus``."""
    with Probe(bus, options.node_id) as probe:
        return run_rules(probe, options)


__all__ = ["RULES", "KitOptions", "RuleResult", "run_conformance"]
