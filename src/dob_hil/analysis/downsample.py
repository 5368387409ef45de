"""Min/max decimation of long series for plotting: every peak survives, at most ``max_points``."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
DEFAULT_MAX_POINTS = 4000


def envelope_indices(y: FloatArray, max_points: int = DEFAULT_MAX_POINTS) -> npt.NDArray[np.int64]:
    """Indices of a min/max decimation of the 1-D ``y``: per bucket the minimum and the maximum,
    in time order (NaN never chosen over a number), plus the last sample: at most
    ``max_points + 1`` indices."""
    n = len(y)
    if n <= max_points:
        return np.arange(n, dtype=np.int64)
    bucket = -(-n // max(max_points // 2, 1))
    nb = -(-n // bucket)  # the last bucket may be partial: padded with NaN, never chosen
    flat = np.full(nb * bucket, np.nan)
    flat[:n] = y
    body = flat.reshape(nb, bucket)
    nan = np.isnan(body)
    lo = np.argmin(np.where(nan, np.inf, body), axis=1)
    hi = np.argmax(np.where(nan, -np.inf, body), axis=1)
    pair = np.sort(np.stack([lo, hi], axis=1), axis=1) + (np.arange(nb) * bucket)[:, None]
    return np.unique(np.concatenate([np.minimum(pair.ravel(), n - 1), [n - 1]])).astype(np.int64)


def envelope(
    t: FloatArray, y: FloatArray, max_points: int = DEFAULT_MAX_POINTS
) -> tuple[FloatArray, FloatArray]:
    """(t, y) decimated by :func:`envelope_indices`."""
    idx = envelope_indices(y, max_points)
    return t[idx], y[idx]
