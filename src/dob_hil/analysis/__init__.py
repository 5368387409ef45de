"""Offline analysis of run logs: metrics, plots, controller replay, bus playback and export.

Modules (each one job):

- :mod:`~dob_hil.analysis.loaded`: read a log and interpret its attachments and metadata
  (:func:`load_log` -> :class:`LoadedLog`);
- :mod:`~dob_hil.analysis.truth_match`: which ground-truth record belongs to which sample;
- :mod:`~dob_hil.analysis.signals`: per-sample derived signals (reference/true/measured output);
- :mod:`~dob_hil.analysis.metrics`: the metrics dictionary (:func:`compute_metrics`);
- :mod:`~dob_hil.analysis.bus_usage`: bus load from the logged frames;
- :mod:`~dob_hil.analysis.model`: the nominal closed loop ("model output" of the paper's figures);
- :mod:`~dob_hil.analysis.plots`, :mod:`~dob_hil.analysis.replay_plot`: PNG plots;
- :mod:`~dob_hil.analysis.table`: the text table;
- :mod:`~dob_hil.analysis.rerun`, :mod:`~dob_hil.analysis.replay`: the controller re-run over a
  log (``replay --verify``, ``replay --design``);
- :mod:`~dob_hil.analysis.frames`, :mod:`~dob_hil.analysis.playback`,
  :mod:`~dob_hil.analysis.export`: the raw frames as python-can messages, onto a bus, into files.

Everything reads the log vectorised (numpy over the structured arrays); only the controller
re-run, the model simulation and the frame playback/export step through samples one by one.
Importing this package loads nothing heavy; matplotlib is imported by the plot functions only.
"""

from __future__ import annotations

from dob_hil.analysis.loaded import LoadedLog, load_log
from dob_hil.analysis.metrics import compute_metrics

__all__ = ["LoadedLog", "compute_metrics", "load_log"]
