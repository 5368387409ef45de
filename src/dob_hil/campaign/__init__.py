"""Robustness campaigns (``dob-hil campaign``): many lockstep runs over perturbed plants,
disturbances and settings, on one machine or a Dask cluster.

Modules (each one job): :mod:`.spec` (the campaign TOML), :mod:`.cases` (seeded draws and
grids, each case's design and truth configs), :mod:`.execute` (one case through
``run_session`` and the analysis metrics), :mod:`.journal` (resume), :mod:`.table` (Parquet),
:mod:`.runners` (serial, process pool, Dask), :mod:`.run` (the whole campaign),
:mod:`.report` (summary, worst cases, plots).
"""
