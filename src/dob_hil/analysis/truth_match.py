"""Which ground-truth record belongs to which sample.

The simulated drive logs one truth record per feedback instant with its ``period_index``; the
host logs sample ``seq``. In lockstep the two count alike (``period_index == seq``). In real
time the host starts counting at the first feedback after enabling, so ``period_index = seq + d``
for a constant offset d (the runner's skips advance ``seq`` by the skipped count, so d stays
constant; a stall of the simulated drive's own timer would change it, which is not modelled).

:func:`match_truth` finds d: the drive's feedback sequence number is its sample count mod 256,
so d = (feedback_seq - seq) mod 256 + 256 j; each candidate j is scored by how well the true
output at ``seq + d`` agrees with the measured output (median absolute difference over an even
spread of samples with feedback), and d = 0 is kept when it agrees within one encoder count
(checked first) or within two of the best candidate. Vectorised: a few thousand candidates
times 64 samples.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]

SCORE_SAMPLES = 64


@dataclass(frozen=True)
class TruthMatch:
    """``index[i]``: the truth row of sample i, or -1. ``offset``: period_index - seq."""

    index: IntArray
    offset: int
    score: float  # median |measured - true output| of the chosen offset (nan: not scored)

    @property
    def matched(self) -> int:
        return int(np.count_nonzero(self.index >= 0))

    def as_slice(self) -> slice | None:
        """The truth rows as one slice when every sample matched consecutive rows (the usual
        case), so that gathering is a view, not a copy; else None."""
        idx = self.index
        if len(idx) == 0:
            return None
        first, last = int(idx[0]), int(idx[-1])
        if first < 0 or last - first != len(idx) - 1:
            return None
        if not np.all(np.diff(idx) == 1):
            return None
        return slice(first, last + 1)


class _Index:
    """Row lookup by period index; O(1) when the indexes are consecutive (the usual case)."""

    def __init__(self, period_index: IntArray) -> None:
        self.n = len(period_index)
        self.first = int(period_index[0]) if self.n else 0
        self.consecutive = self.n > 0 and bool(
            int(period_index[-1]) - self.first == self.n - 1 and np.all(np.diff(period_index) == 1)
        )
        if self.consecutive:
            self.keys = period_index[:1]
            self.order = np.zeros(1, dtype=np.int64)
        else:
            self.order = np.argsort(period_index, kind="stable").astype(np.int64)
            self.keys = period_index[self.order]

    @property
    def lo(self) -> int:
        return self.first if self.consecutive else int(self.keys[0])

    @property
    def hi(self) -> int:
        return self.first + self.n - 1 if self.consecutive else int(self.keys[-1])

    def rows(self, wanted: IntArray) -> IntArray:
        """Row of each wanted period index, or -1."""
        if self.consecutive:
            rel = wanted - self.first
            return np.where((rel >= 0) & (rel < self.n), rel, -1)
        pos = np.searchsorted(self.keys, wanted)
        pos_c = np.minimum(pos, self.n - 1)
        hit = (pos < self.n) & (self.keys[pos_c] == wanted)
        return np.where(hit, self.order[pos_c], -1)


def match_truth(
    seq: IntArray,
    feedback_seq: IntArray,
    has_feedback: npt.NDArray[np.bool_],
    y_measured: FloatArray,
    period_index: IntArray,
    true_output: Callable[[IntArray], FloatArray],
    quantum: float,
) -> TruthMatch:
    """Match samples to truth records (module docstring). ``y_measured`` (n x p);
    ``true_output(rows)``: the true output of those truth rows (len(rows) x p), in the same unit;
    ``quantum``: one encoder count in that unit (the tie tolerance)."""
    n = len(seq)
    if n == 0 or len(period_index) == 0:
        return TruthMatch(np.full(n, -1, dtype=np.int64), 0, float("nan"))
    index = _Index(period_index)
    valid = np.flatnonzero(has_feedback)
    if len(valid) == 0:  # nothing to score with: trust the lockstep convention
        return TruthMatch(index.rows(seq), 0, float("nan"))
    pick = valid[np.linspace(0, len(valid) - 1, min(SCORE_SAMPLES, len(valid))).astype(np.int64)]
    y_pick = y_measured[pick]
    rows0 = index.rows(seq[pick])
    if np.all(rows0 >= 0):  # the lockstep convention fits to within an encoder count: keep it
        score0 = float(np.median(np.abs(true_output(rows0) - y_pick).max(axis=1)))
        if score0 <= quantum:
            return TruthMatch(index.rows(seq), 0, score0)
    d0 = int(np.argmax(np.bincount((feedback_seq[valid] - seq[valid]) % 256, minlength=256)))
    lo = index.lo - int(seq.max())
    hi = index.hi - int(seq.min())
    first = d0 + 256 * ((lo - d0) // 256)
    candidates = np.unique(np.concatenate([[0], np.arange(first, hi + 1, 256, dtype=np.int64)]))
    rows = index.rows(seq[pick][None, :] + candidates[:, None])  # (candidates, picks)
    y_true = true_output(np.maximum(rows, 0).ravel()).reshape(*rows.shape, -1)
    diff = np.abs(y_true - y_pick[None, :, :]).max(axis=2)
    diff = np.where(rows >= 0, diff, np.inf)
    present = (rows >= 0).sum(axis=1)
    scores = np.where(2 * present >= len(pick), np.median(diff, axis=1), np.inf)
    best = int(np.argmin(scores))
    zero = int(np.flatnonzero(candidates == 0)[0])
    if np.isfinite(scores[zero]) and scores[zero] <= scores[best] + 2.0 * quantum:
        best = zero
    if not np.isfinite(scores[best]):
        return TruthMatch(np.full(n, -1, dtype=np.int64), 0, float("nan"))
    offset = int(candidates[best])
    return TruthMatch(index.rows(seq + offset), offset, float(scores[best]))
