"""Opt-in OS settings for the real-time loop: SCHED_FIFO, CPU affinity, a frozen GC.

Each is applied where the OS permits and reported otherwise; none is silently skipped. Measured
on this kind of machine (BENCHMARKS.md, real-time rows): SCHED_FIFO + pinning + gc.freeze() cut the worst
lateness of a 300 us loop by an order of magnitude; gen-2 GC pauses are 6-8 ms.
"""

from __future__ import annotations

import contextlib
import gc
import os
from dataclasses import dataclass, field


@dataclass
class RtSettings:
    sched_fifo: bool = False
    fifo_priority: int = 50
    cpus: tuple[int, ...] | None = None
    freeze_gc: bool = False


@dataclass
class RtReport:
    applied: list[str] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)
    previous_cpus: set[int] | None = None  # the affinity before, restored by restore_rt_settings


def apply_rt_settings(settings: RtSettings) -> RtReport:
    report = RtReport()
    if settings.cpus:
        try:
            report.previous_cpus = os.sched_getaffinity(0)
            os.sched_setaffinity(0, set(settings.cpus))
            report.applied.append(f"CPU affinity {sorted(settings.cpus)}")
        except (OSError, AttributeError, ValueError) as exc:
            report.refused.append(f"CPU affinity {sorted(settings.cpus)}: {exc}")
    if settings.sched_fifo:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(settings.fifo_priority))
            report.applied.append(f"SCHED_FIFO priority {settings.fifo_priority}")
        except PermissionError:
            report.refused.append(
                "SCHED_FIFO: not permitted (needs root or CAP_SYS_NICE, or an rtprio limit in "
                "/etc/security/limits.conf); running with the normal scheduler"
            )
        except (OSError, AttributeError) as exc:
            report.refused.append(f"SCHED_FIFO: {exc}")
    if settings.freeze_gc:
        gc.collect()
        gc.freeze()
        gc.disable()
        report.applied.append("gc.freeze() + gc.disable() (no GC pauses in the loop)")
    return report


def restore_rt_settings(settings: RtSettings, report: RtReport | None = None) -> None:
    """Undo :func:`apply_rt_settings` (the CPU affinity only when given its ``report``)."""
    if report is not None and report.previous_cpus:
        with contextlib.suppress(OSError, AttributeError, ValueError):
            os.sched_setaffinity(0, report.previous_cpus)
    if settings.freeze_gc:
        gc.enable()
        gc.unfreeze()
    if settings.sched_fifo:
        with contextlib.suppress(OSError, AttributeError):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
