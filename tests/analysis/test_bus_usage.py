"""Bus load from frames on either clock (simulated sample time or the loop's monotonic clock)."""

from __future__ import annotations

import numpy as np
import pytest

from dob_hil.analysis.bus_usage import bus_load, clock_offset_ns, counted_frames
from dob_hil.link.busload import frame_bits
from dob_hil.log import LogLayout
from dob_hil.log.schemas import CAN_FLAG_ERROR, CAN_FLAG_EXTENDED, can_fields, msg_dtype, sample_fields

PERIOD_NS = 300_000
N = 2000
LAYOUT = LogLayout(2, 1, 1, 2)


def _run(on_monotonic: bool, echo: bool) -> tuple[np.ndarray, np.ndarray]:
    """N samples, each with a 6-byte FEEDBACK (rx) and a 3-byte COMMAND (tx); an enable CONTROL
    before the first; a 29-bit foreign frame every 100 periods; an error frame once."""
    rng = np.random.default_rng(5)
    samples = np.zeros(N, dtype=msg_dtype(sample_fields(LAYOUT)))
    k = np.arange(N, dtype=np.int64)
    samples["time_ns"] = k * PERIOD_NS
    start = 7_000_000_000
    rx = start + k * PERIOD_NS + rng.integers(0, 60_000, N)  # jittered real-time schedule
    samples["rx_time_ns"] = rx
    samples["tx_time_ns"] = rx + 15_000
    samples["seq"] = k
    rows: list[tuple[int, int, int, int, int]] = [
        (int(rx[0]) - 50_000 if on_monotonic else 0, 0x601, 1, 1, 0)
    ]
    for i in range(N):
        t_fb = int(rx[i]) - 2_000 if on_monotonic else i * PERIOD_NS
        t_cmd = int(rx[i]) + 14_000 if on_monotonic else i * PERIOD_NS
        rows += [(t_fb, 0x181, 0, 6, 0), (t_cmd, 0x201, 1, 3, 0)]
        if echo:
            rows.append((t_cmd + 1_000, 0x201, 0, 3, 0))
        if i % 100 == 50:
            rows.append((t_fb + 1, 0x1234567, 0, 8, CAN_FLAG_EXTENDED))
    rows.append((rows[-1][0] + 1, 0x20000080, 0, 8, CAN_FLAG_ERROR))
    frames = np.zeros(len(rows), dtype=msg_dtype(can_fields()))
    for name, j in (("timestamp_ns", 0), ("arbitration_id", 1), ("direction", 2), ("dlc", 3), ("flags", 4)):
        frames[name] = [r[j] for r in rows]
    return samples, frames


@pytest.mark.parametrize("on_monotonic", [False, True])
@pytest.mark.parametrize("echo", [False, True])
def test_bus_load_counts_each_frame_once(on_monotonic: bool, echo: bool) -> None:
    samples, frames = _run(on_monotonic, echo)
    aligned = clock_offset_ns(samples, frames)
    assert aligned is not None
    assert aligned[0] == ("tx_time_ns" if on_monotonic else "time_ns")
    assert abs(aligned[1] - (-1_000 if on_monotonic else 0)) <= 1_000
    first = 1000
    load = bus_load(samples, frames, frames[:0], first, PERIOD_NS, 1_000_000)
    assert load is not None
    n = N - first
    foreign = sum(1 for i in range(first, N) if i % 100 == 50)
    bits = n * (frame_bits(6) + frame_bits(3)) + foreign * frame_bits(8, extended_id=True)
    assert load["frames"] == 2 * n + foreign
    assert load["worst_case"] == pytest.approx(bits / 1e6 / (n * PERIOD_NS * 1e-9))
    assert load["bits_per_period_worst_case"] == pytest.approx(bits / n)
    assert counted_frames(frames).sum() == len(frames) - 1 - (N if echo else 0)
