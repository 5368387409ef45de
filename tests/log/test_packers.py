"""The generated LogWriter.sample (dob_hil.log.packers) writes the same bytes as the general
method, for several layouts, and hands anything unusual to it (same errors)."""

from __future__ import annotations

import functools
import os
import random
import re
import threading

import numpy as np
import pytest

from dob_hil.errors import LogWriteError
from dob_hil.log.schemas import LogLayout
from dob_hil.log.writer import LogWriter


def _args(rng: random.Random, layout: LogLayout) -> tuple[object, ...]:
    n, m, p = layout.n_states, layout.n_inputs, layout.n_outputs

    def floats(k: int) -> tuple[float, ...]:
        return tuple(rng.uniform(-1e3, 1e3) for _ in range(k))

    return (
        rng.randrange(2**40), rng.randrange(2**40), rng.randrange(2**40), rng.randrange(-(2**40), 2**40),
        tuple(rng.randrange(-(2**40), 2**40) for _ in range(p)), floats(p), floats(n), floats(n),
        floats(n), floats(m), floats(m), floats(m), floats(m), rng.randrange(2**32), rng.randrange(2**32),
        tuple(rng.randrange(-(2**31), 2**31) for _ in range(m)), rng.randrange(256), rng.randrange(256),
    )  # fmt: skip


@pytest.mark.parametrize("layout", [LogLayout(2, 1, 1, 2), LogLayout(3, 1, 1, 2), LogLayout(6, 2, 2, 4)])
def test_generated_sample_writes_the_same_bytes(layout: LogLayout) -> None:
    rng = random.Random(layout.n_states)
    with LogWriter(os.devnull, layout) as fast, LogWriter(os.devnull, layout) as general:
        assert "sample" in vars(fast)  # an instance attribute: the generated method
        write_general = functools.partial(LogWriter.sample, general)
        for _ in range(200):
            args = _args(rng, layout)
            fast.sample(*args)
            write_general(*args)
            assert bytes(fast._batch) == bytes(general._batch)
            assert fast._batch_records == general._batch_records
        # lists and numpy arrays unpack as tuples do
        args = list(_args(rng, layout))
        args[6] = np.asarray(args[6])
        args[7] = list(args[7])  # type: ignore[call-overload]
        fast.sample(*args)
        write_general(*args)
        assert bytes(fast._batch) == bytes(general._batch)
        assert fast._seq_sample == general._seq_sample == 201


def test_generated_sample_hands_bad_values_to_the_general_method() -> None:
    layout = LogLayout(2, 1, 1, 2)
    with LogWriter(os.devnull, layout) as log:
        args = list(_args(random.Random(1), layout))
        short = list(args)
        short[6] = (0.5,)  # x_ref: one value instead of two
        with pytest.raises(LogWriteError, match=r"sample\.x_ref: expected 2 values, got 1"):
            log.sample(*short)
        bad = list(args)
        bad[13] = -1  # seq: uint32
        with pytest.raises(LogWriteError, match=r"sample\.seq"):
            log.sample(*bad)
        assert log._seq_sample == 0 and not log._batch
        log.sample(*args)
        assert log._seq_sample == 1


def test_generated_sample_from_another_thread_queues_the_record() -> None:
    layout = LogLayout(2, 1, 1, 2)
    with LogWriter(os.devnull, layout) as log, LogWriter(os.devnull, layout) as general:
        args = _args(random.Random(2), layout)
        worker = threading.Thread(target=log.sample, args=args)
        worker.start()
        worker.join()
        assert len(log._foreign) == 1 and not log._batch and log._seq_sample == 1
        LogWriter.sample(general, *args)
        assert bytes(log._foreign[0]) == bytes(general._batch)


class _Subclass(LogWriter):
    def sample(self, *args: object) -> None:  # type: ignore[override]
        self.got = args


def test_a_subclass_keeps_its_own_sample() -> None:
    with _Subclass(os.devnull, LogLayout(2, 1, 1, 2)) as log:
        assert "sample" not in vars(log)
        log.sample(1, 2)
        assert log.got == (1, 2)


def test_the_generated_source_is_built_from_dimensions_only() -> None:
    """Identifiers and array indices only: no value of any record or config is turned into code."""
    with LogWriter(os.devnull, LogLayout(3, 1, 1, 2)) as log:
        source: str = log.sample.source  # type: ignore[attr-defined]
    assert "x_ref_0, x_ref_1, x_ref_2, = x_ref" in source
    for literal in re.findall(r"(?<![\w.])\d[\w.]*", source):
        assert literal == "1"  # only the record counter's "+ 1"; every other number is bound


@pytest.mark.parametrize("n_plant_states", [1, 2, 4])
def test_truth_hook_writes_what_truth_writes(n_plant_states: int) -> None:
    layout = LogLayout(2, 1, 1, n_plant_states)
    rng = random.Random(n_plant_states)
    with LogWriter(os.devnull, layout) as fast, LogWriter(os.devnull, layout) as general:
        sink = fast.truth_hook()  # stages the tuple; the generated record packs it
        assert "state_0" in fast._truth_records.source  # type: ignore[union-attr]
        for k in range(100):
            state = tuple(rng.uniform(-5.0, 5.0) for _ in range(n_plant_states))
            d, a = rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0)
            sink((k, k * 300_000, state, d, a, 1))
            fast._pack_staged()
            general.truth(k * 300_000, state, (d,), (a,), k, 1)
            assert bytes(fast._batch) == bytes(general._batch)
        sink((0, 0, (1.0,) * (n_plant_states + 1), 0.0, 0.0, 1))
        with pytest.raises(LogWriteError, match=r"truth\.state: expected"):
            fast._pack_staged()
        assert fast._seq_truth == 100
