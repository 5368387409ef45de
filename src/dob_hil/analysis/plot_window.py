"""The stretch of a log that ``dob-hil analyze`` plots: all of a short log, a window of a long one.

A long log (more samples than ``dob-hil analyze`` holds in memory, see
``commands.analyze.STREAM_ABOVE_SAMPLES``) has its metrics computed streamed over its whole length,
and its plots drawn from a window of at most :data:`MAX_WINDOW_SAMPLES` samples: by default its
first ``STREAM_ABOVE_SAMPLES`` samples (the start-up and the first transients), or the window the
user gives with ``--plot-window START:END`` (seconds from the first sample). The window is read
with the MCAP chunk index (:func:`dob_hil.log.read_log` ``log_time_window_ns``): only the chunks it
overlaps are decompressed, so memory is bounded by the window, whatever the log's length. Times
in the plots stay relative to the log's first sample.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from dob_hil.analysis.loaded import ANALYSIS_FIELDS, LoadedLog, interpret
from dob_hil.analysis.signals import Signals, derive_signals
from dob_hil.errors import ConfigError
from dob_hil.log import read_log

# A window of a long log holds at most this many samples (about 100 MB of analysis arrays).
MAX_WINDOW_SAMPLES = 400_000


def parse_plot_window(text: str) -> tuple[float, float]:
    """``START:END`` in seconds (0 <= START < END, both finite) -> (start_s, end_s)."""
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        start_s, end_s = float(parts[0]), float(parts[1])
    except ValueError:
        problem = f"expected START:END in seconds (e.g. 60:90), got {text!r}"
        raise ConfigError("--plot-window", problem) from None
    if not (math.isfinite(start_s) and math.isfinite(end_s) and 0.0 <= start_s < end_s):
        raise ConfigError("--plot-window", f"needs finite seconds with 0 <= START < END, got {text!r}")
    return start_s, end_s


def _span_s(t0_ns: int, last_ns: int) -> str:
    return f"0-{(last_ns - t0_ns) * 1e-9:.6g} s"


def window_of_long_log(
    path: Path, t0_ns: int, last_ns: int, period_ns: int | None, window_s: tuple[float, float]
) -> tuple[LoadedLog, Signals]:
    """The window ``window_s`` of a long log, read by the chunk index, and its signals.

    Raises ConfigError when the window would hold more than :data:`MAX_WINDOW_SAMPLES` samples or
    holds none."""
    start_s, end_s = window_s
    if period_ns and (end_s - start_s) * 1e9 / period_ns > MAX_WINDOW_SAMPLES:
        longest_s = MAX_WINDOW_SAMPLES * period_ns * 1e-9
        raise ConfigError(
            "--plot-window",
            f"{start_s:g}:{end_s:g} s is more than {MAX_WINDOW_SAMPLES:,} samples of {path}; "
            f"plot at most {longest_s:g} s of it at a time",
        )
    first_ns = t0_ns + round(start_s * 1e9)
    last_wanted_ns = t0_ns + round(end_s * 1e9)
    data = read_log(path, fields=ANALYSIS_FIELDS, log_time_window_ns=(first_ns, last_wanted_ns))
    t_ns = data.samples["time_ns"].view(np.int64)
    keep = (t_ns >= first_ns) & (t_ns <= last_wanted_ns)
    if not keep.any():
        raise ConfigError(
            "--plot-window",
            f"{start_s:g}:{end_s:g} s holds no samples of {path} (it spans {_span_s(t0_ns, last_ns)})",
        )
    data.samples = data.samples[keep]
    log = interpret(path, data)
    return log, derive_signals(log, t0_ns)


def window_of_loaded_log(log: LoadedLog, window_s: tuple[float, float]) -> tuple[LoadedLog, Signals]:
    """The window ``window_s`` of a log already read whole, and its signals (times from its first
    sample). Raises ConfigError when the window holds no samples."""
    samples = log.data.samples
    t_ns = samples["time_ns"].view(np.int64)
    if len(t_ns) == 0:
        return log, derive_signals(log)
    t0_ns = int(t_ns[0])
    start_s, end_s = window_s
    keep = (t_ns >= t0_ns + round(start_s * 1e9)) & (t_ns <= t0_ns + round(end_s * 1e9))
    if not keep.any():
        raise ConfigError(
            "--plot-window",
            f"{start_s:g}:{end_s:g} s holds no samples of {log.path} "
            f"(it spans {_span_s(t0_ns, int(t_ns[-1]))})",
        )
    log.data.samples = samples[keep]
    return log, derive_signals(log, t0_ns)


__all__ = ["MAX_WINDOW_SAMPLES", "parse_plot_window", "window_of_loaded_log", "window_of_long_log"]
