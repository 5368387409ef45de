"""Shared helpers of the multi-axis tests: the shipped 2x2 scenario, variants, truth matching."""

from __future__ import annotations

import dataclasses

import numpy as np
import numpy.typing as npt

from dob_hil.config import Config, parse_config_text
from dob_hil.log import LogData
from dob_hil.scenarios import scenario_path

FloatArray = npt.NDArray[np.float64]


def mimo_text(replace: dict[str, str] | None = None, append: str = "") -> str:
    """The scenario's TOML with exact lines replaced and text appended."""
    text = scenario_path("mimo-2x2").read_text()
    for old, new in (replace or {}).items():
        assert old in text, old
        text = text.replace(old, new)
    return text + append


def mimo_config(replace: dict[str, str] | None = None, append: str = "") -> Config:
    return parse_config_text(mimo_text(replace, append), source=scenario_path("mimo-2x2"))


def patient(config: Config, periods: int) -> Config:
    """``config`` with the drive's watchdog and the host timeout widened to ``periods``."""
    drive = dataclasses.replace(config.drive, watchdog_periods=periods, feedback_timeout_periods=periods)
    return dataclasses.replace(config, drive=drive)


STALL_PERIODS = 10  # a gap of this many periods or more is a stall, not real-time jitter


def undisturbed_truth(data: LogData, settle_s: float) -> npt.NDArray[np.bool_]:
    """Real time on a loaded machine: the truth records (in the log's order) that no stall of the
    loop preceded within ``settle_s``. A stall is a gap of :data:`STALL_PERIODS` periods or more:
    in the drive's period index (its timer thread fell behind and integrated the gap with the
    held current), or in the loop's answers (a ``stall`` event, or a skip or loss of that many
    samples); each throws the plant off its course for a transient. A period or two skipped now
    and then is real time as it is, and is kept. In lockstep nothing stalls: every record is kept.
    """
    t = data.truth
    t_ns = t["time_ns"].astype(np.int64)
    order = np.argsort(t_ns, kind="stable")
    steps = np.diff(t["period_index"][order].astype(np.int64))
    upsets = [t_ns[order][1:][steps >= STALL_PERIODS]]
    host = [
        e["time_ns"]
        for e in data.events
        if e["kind"] == "stall"
        or (
            e["kind"] in ("overrun_skip", "feedback_lost") and int(e["data"].get("count", 0)) >= STALL_PERIODS
        )
    ]
    upsets.append(np.array(host, dtype=np.int64))
    bad = np.sort(np.concatenate(upsets))
    if bad.size == 0:  # an undisturbed run
        return np.ones(len(t_ns), dtype=bool)
    i = np.searchsorted(bad, t_ns, side="right")
    last_bad = np.where(i > 0, bad[np.maximum(i - 1, 0)], np.iinfo(np.int64).min // 2)
    return np.asarray(t_ns - last_bad > settle_s * 1e9)


def steady_tracking_rms(
    data: LogData,
    C_design: FloatArray,
    C_plant: FloatArray,
    from_sample: int,
    keep: npt.NDArray[np.bool_] | None = None,
) -> FloatArray:
    """RMS of reference minus *true* output (ground truth ``C x``), per output, over the truth
    records from sample ``from_sample``'s instant to the last sample's, while the reference holds
    still (checked: the scenario's steps are settled by then).

    Only the drive's own records are used (no pairing of samples with truth records by time, which
    real time cannot make exact). The reference is indexed by sample (every sample is logged, in
    order), so the window starts at a sample, not at a time: in real time a stall can put sample k
    well after ``k Ts``.
    """
    s, t = data.samples, data.truth
    ref = s["x_ref"] @ C_design.T
    setpoint = ref[-1]
    np.testing.assert_allclose(
        ref[from_sample:], np.broadcast_to(setpoint, ref[from_sample:].shape), atol=1e-12
    )
    t_ns = t["time_ns"].astype(np.int64)
    enabled = t["drive_state"] == 1
    window = enabled & (t_ns >= int(s["time_ns"][from_sample])) & (t_ns <= int(s["time_ns"][-1]))
    if keep is None:
        assert np.count_nonzero(window) > 0.5 * (len(s) - from_sample), "too few truth records"
    else:
        window &= keep
    err = setpoint - t["state"][window] @ C_plant.T
    return np.asarray(np.sqrt(np.mean(err**2, axis=0)), dtype=np.float64)
