"""Matching ground truth to samples: the offset between the drive's period index and the host's seq."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dob_hil.analysis.truth_match import match_truth

QUANTUM = 1e-4


def _trajectory(k: np.ndarray) -> np.ndarray:
    return (np.sin(2 * np.pi * k / 3333.0) + 0.2 * np.sin(2 * np.pi * k / 277.0))[:, None]


def _case(n: int, truth_lead: int, offset: int, extra: int = 50) -> tuple[np.ndarray, ...]:
    period_index = np.arange(truth_lead, truth_lead + n + offset + extra, dtype=np.int64)
    seq = np.arange(n, dtype=np.int64)
    y_meas = np.round(_trajectory(seq + offset) / QUANTUM) * QUANTUM
    return seq, (seq + offset) % 256, np.ones(n, dtype=bool), y_meas, period_index


@settings(max_examples=40, deadline=None)
@given(offset=st.integers(0, 5000), n=st.integers(300, 3000))
def test_finds_the_offset_of_a_realtime_run(offset: int, n: int) -> None:
    seq, fb_seq, has_fb, y_meas, period_index = _case(n, 0, offset)
    m = match_truth(
        seq, fb_seq, has_fb, y_meas, period_index, lambda r: _trajectory(period_index[r]), QUANTUM
    )
    assert m.offset == offset
    assert np.array_equal(period_index[m.index], seq + offset)
    assert m.score <= QUANTUM


def test_lockstep_offset_zero_also_when_the_plant_is_still() -> None:
    """A still plant matches every offset equally well: zero (the lockstep convention) wins."""
    n = 2000
    seq = np.arange(n, dtype=np.int64)
    period_index = np.arange(n + 1, dtype=np.int64)
    m = match_truth(
        seq,
        seq % 256,
        np.ones(n, dtype=bool),
        np.ones((n, 1)),
        period_index,
        lambda r: np.ones((len(r), 1)),
        QUANTUM,
    )
    assert m.offset == 0 and m.as_slice() == slice(0, n)


def test_unmatched_samples_get_minus_one_and_no_slice() -> None:
    seq, fb_seq, has_fb, y_meas, period_index = _case(1000, 0, 0)
    keep = np.ones(len(period_index), dtype=bool)
    keep[100:110] = False  # ten truth records lost
    pi = period_index[keep]
    m = match_truth(seq, fb_seq, has_fb, y_meas, pi, lambda r: _trajectory(pi[r]), QUANTUM)
    assert m.offset == 0
    assert np.array_equal(np.flatnonzero(m.index < 0), np.arange(100, 110))
    assert m.matched == 990 and m.as_slice() is None


@pytest.mark.parametrize("n_truth", [0, 5])
def test_no_feedback_or_too_little_truth(n_truth: int) -> None:
    seq = np.arange(100, dtype=np.int64)
    pi = np.arange(n_truth, dtype=np.int64)
    m = match_truth(
        seq,
        seq % 256,
        np.zeros(100, dtype=bool),
        np.zeros((100, 1)),
        pi,
        lambda r: np.zeros((len(r), 1)),
        QUANTUM,
    )
    assert m.offset == 0 and m.matched == n_truth
