"""The streamed, vectorised replay --verify gives the chained re-run's verdict, in every branch of
the missing-feedback policies, across block boundaries, and hands mismatches to the chained path."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from analysis_support import rewrite_log, run_log, scenario_text
from test_replay_cycle import LOST, MISSING, _write_run

from dob_hil.analysis import load_log, verify_fast
from dob_hil.analysis.replay import verify
from dob_hil.config import parse_config_text
from dob_hil.log import read_log
from dob_hil.log.schemas import TOPIC_EVENT


def _both(path: Path, monkeypatch: pytest.MonkeyPatch, block: int | None = None) -> tuple[object, object]:
    chained = verify(load_log(path))
    if block is not None:
        samples = read_log(path).samples

        def small_blocks(_: Path) -> Iterator[np.ndarray]:
            for i in range(0, len(samples), block):
                yield samples[i : i + block]

        monkeypatch.setattr(verify_fast, "_blocks", small_blocks)
    fast = verify_fast.verify_streaming(load_log(path, topics=[TOPIC_EVENT]))
    return chained, fast


@pytest.mark.parametrize("block", [None, 7])
@pytest.mark.parametrize(("policy", "dob"), [("hold", True), ("extrapolate", False), ("zero", True)])
def test_every_branch_of_the_cycle_gives_the_chained_verdict(
    tmp_path: Path, policy: str, dob: bool, block: int | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    text = scenario_text(
        "paper-step",
        **{
            "dob_enabled = true\n": f"dob_enabled = true\n"
            f"missing_feedback_policy = '{policy}'\nmax_missing_periods = 2\n"
        },
    )
    path = tmp_path / f"{policy}.mcap"
    _write_run(path, parse_config_text(text), dob)
    assert MISSING and LOST
    chained, fast = _both(path, monkeypatch, block)
    assert chained.identical  # type: ignore[attr-defined]
    assert fast is not None and fast.identical  # type: ignore[attr-defined]
    assert fast.samples == chained.samples and set(fast.fields) == set(chained.fields)  # type: ignore[attr-defined]


@pytest.mark.parametrize("policy", ["hold", "extrapolate", "zero"])
def test_real_runs_with_lost_feedback(tmp_path: Path, policy: str, monkeypatch: pytest.MonkeyPatch) -> None:
    text = scenario_text(
        "paper-sine",
        **{
            "seed = 0\n": "seed = 3\nloss_probability = 0.05\n",
            "dob_enabled = true\n": f"dob_enabled = true\nmissing_feedback_policy = '{policy}'\n"
            "max_missing_periods = 1\n",
        },
    )
    path = run_log(tmp_path / f"{policy}.mcap", text, dob=True, duration_s=0.2)
    chained, fast = _both(path, monkeypatch, 64)
    assert chained.identical and fast is not None and fast.identical  # type: ignore[attr-defined]


def test_a_gap_in_the_log_restarts_like_the_chain(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    data = read_log(runs[("paper-step", True)])
    keep = np.ones(len(data.samples), dtype=bool)
    keep[400:410] = False
    path = rewrite_log(data, tmp_path / "gap.mcap", samples=data.samples[keep])
    chained, fast = _both(path, monkeypatch, 100)
    assert fast is not None and fast.identical and fast.resyncs == chained.resyncs == [410]  # type: ignore[attr-defined]


@pytest.mark.parametrize("field", ["u_cmd_a", "x_bar", "x_ref", "dac_counts"])
def test_a_one_ulp_difference_goes_to_the_chained_path(
    runs: dict[tuple[str, bool], Path], tmp_path: Path, field: str
) -> None:
    data = read_log(runs[("paper-sine", True)])
    samples = data.samples.copy()
    if field == "dac_counts":
        samples[field][500, 0] += 1
    else:
        samples[field][500, 0] = np.nextafter(samples[field][500, 0], np.inf)
    path = rewrite_log(data, tmp_path / f"tampered-{field}.mcap", samples=samples)
    assert verify_fast.verify_streaming(load_log(path, topics=[TOPIC_EVENT])) is None
    assert not verify(load_log(path)).identical


def test_the_vector_quantizer_is_the_drive_quantizer() -> None:
    from dob_hil.config import DriveConfig
    from dob_hil.link.native import DacQuantizer

    drive = DriveConfig(current_limit_A=0.7, dac_lsb_A=0.001)
    vq, dq = verify_fast.VectorQuantizer(drive), DacQuantizer(drive)
    rng = np.random.default_rng(1)
    u = np.concatenate(
        [rng.uniform(-1.0, 1.0, 20_000), (np.arange(-800, 801) + 0.5) * 0.001, [np.nan, np.inf]]
    )
    codes, applied, sat = vq(u)
    for i, value in enumerate(u.tolist()):
        (code,), (amps,), saturated = dq.quantize((value,))
        assert (code, amps, saturated) == (int(codes[i]), float(applied[i]), bool(sat[i])), value


@pytest.mark.parametrize("scenario", ["paper-sine", "paper-step"])
def test_reference_rows_are_at_k_bit_for_bit_with_gaps(scenario: str) -> None:
    from dob_hil.control.reference import make_reference

    config = parse_config_text(scenario_text(scenario))
    reference = make_reference(config.reference, 2, config.plant.period_s)
    for seq in (
        np.arange(1000, 3000, dtype=np.int64),
        np.concatenate([np.arange(0, 500), np.arange(520, 900)]).astype(np.int64),  # small gaps: block
        np.asarray([5, 10**7, 10**7 + 1], dtype=np.int64),  # a huge gap: one at() per sample
    ):
        rows = verify_fast.reference_rows(reference, seq)
        expected = np.asarray([reference.at(k) for k in seq.tolist()], dtype=np.float64)
        assert np.array_equal(rows.view(np.uint64), expected.view(np.uint64))
