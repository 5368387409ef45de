"""Straight-line record packing generated for a log layout's dimensions (the per-period path).

:meth:`dob_hil.log.writer.LogWriter.sample` packs its record with ``pack(..., *counts,
*position, *x_ref, ...)``: ten starred arguments, which CPython gathers into a list and a tuple
on every call (about 0.3 us of a lockstep sample). :func:`compile_sample` generates the same
method for fixed array sizes, each array unpacked into named locals and handed to ``pack`` as
plain positional arguments: the same record, byte for byte. As in :mod:`dob_hil.control.step`,
the source is built from the *dimensions and field names only* (identifiers such as
``x_ref_1``); every object it uses enters as a default argument, so no data from a config or a
log is ever turned into code. Anything unusual (an array of another length, a value that does not
pack) goes to the general method, which packs it or raises the error naming the field. The
source is run by :func:`dob_hil.control.step.run_generated`, the source tree's one ``exec``.
"""

from __future__ import annotations

import struct
import threading
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from dob_hil.control.step import run_generated
from dob_hil.log.schemas import CDR_HEADER_U32, CH_SAMPLE, CH_TRUTH, OP_MESSAGE, Field

_U32 = 0xFFFFFFFF


class _Batching(Protocol):
    """The writer state the generated method updates (LogWriter's owner-thread batch)."""

    _seq_sample: int
    _seq_truth: int
    _owner: int
    _batch: bytearray
    _batch_records: int
    _next_bytes: int
    _foreign: Any

    def _batch_due(self) -> None: ...

    def _restage_truth(self, rest: list[tuple[Any, ...]]) -> None: ...


# the parameters of LogWriter.sample, in order, and the sample field each one fills
SAMPLE_PARAMS: tuple[str, ...] = (
    "time_ns", "rx_time_ns", "tx_time_ns", "lateness_ns", "counts", "position", "x_ref", "x_hat",
    "x_bar", "u_fb", "u_dist", "u_cmd_A", "u_applied_A", "seq", "compute_ns", "dac_counts",
    "feedback_seq", "flags",
)  # fmt: skip


def compile_sample(
    writer: _Batching,
    fields: Sequence[Field],
    pack: Callable[..., bytes],
    length: int,
    general: Callable[..., None],
) -> Callable[..., None]:
    """``sample(time_ns, rx_time_ns, ...)`` with :data:`SAMPLE_PARAMS`: the record of ``fields``
    (the sample fields, in :data:`SAMPLE_PARAMS` order) packed by ``pack`` with the record length
    ``length``, appended to ``writer``'s batch as ``LogWriter.sample`` does; ``general`` (that
    method) takes every call whose arrays do not unpack or whose values do not pack."""
    if len(fields) != len(SAMPLE_PARAMS):
        raise ValueError(f"expected {len(SAMPLE_PARAMS)} sample fields, got {len(fields)}")
    unpack_lines: list[str] = []
    values: list[str] = []
    for param, field in zip(SAMPLE_PARAMS, fields, strict=True):
        if field.count is None:
            values.append(param)
            continue
        names = [f"{param}_{i}" for i in range(field.count)]
        unpack_lines.append(f"        {''.join(f'{v}, ' for v in names)}= {param}")
        values.extend(names)
    params = ", ".join(SAMPLE_PARAMS)
    source = (
        f"def sample({params}, _w=_w, _pack=_pack, _general=_general, _get_ident=_get_ident):\n"
        "    n = _w._seq_sample\n"
        "    try:\n"
        + "\n".join(unpack_lines)
        + "\n        record = _pack(_OP, _LEN, _CH, n & _U32, time_ns, time_ns, _CDR, "
        + ", ".join(values)
        + ")\n"
        "    except (ValueError, TypeError, _StructError):\n"
        f"        return _general({params})\n"
        "    _w._seq_sample = n + 1\n"
        "    if _get_ident() == _w._owner:\n" + _append("        ") + "    else:\n"
        "        _w._foreign.append(record)\n"
        "    return None\n"
    )
    return _define("sample", source, writer, pack, length, CH_SAMPLE, general)


def _append(indent: str) -> str:
    """The owner thread's append of ``record`` to the batch (LogWriter._append, inline)."""
    lines = (
        "batch = _w._batch",
        "batch += record",
        "_w._batch_records += 1",
        "if len(batch) >= _w._next_bytes:",
        "    _w._batch_due()",
    )
    return "".join(f"{indent}{line}\n" for line in lines)


def compile_truth_records(
    writer: _Batching,
    n_plant_states: int,
    pack: Callable[..., bytes],
    length: int,
    general: Callable[[tuple[Any, ...]], None],
) -> Callable[[list[tuple[Any, ...]]], None]:
    """``records(staged)`` for a run of a single-axis drive's ground truth tuples ``(period_index,
    time_ns, state, disturbance_A, applied_current_A, drive_state)`` with ``n_plant_states``
    states: each truth record packed by ``pack`` (record length ``length``) and appended to
    ``writer``'s batch in one loop, as ``LogWriter.truth`` would. For the owner thread's packing
    of staged truth (``LogWriter._pack_staged``, which takes care of the batch's length): no
    thread check and no length check. ``general(truth)`` takes a multi-axis drive's truth (a
    tuple per input) and anything that does not unpack or pack; should it raise, the truths after
    the one that raised are handed to ``writer._restage_truth`` before the error propagates."""
    names = [f"state_{i}" for i in range(n_plant_states)]
    source = (
        "def records(staged, _w=_w, _pack=_pack, _general=_general):\n"
        "    n = base = _w._seq_truth\n"
        "    batch = _w._batch\n"
        "    i = 0\n"
        "    try:\n"
        "        for i, t in enumerate(staged):\n"
        "            try:\n"
        "                period_index, time_ns, state, disturbance_A, applied_A, drive_state = t\n"
        "                if type(disturbance_A) is not tuple:\n"
        f"                    {''.join(f'{v}, ' for v in names)}= state\n"
        "                    batch += _pack(_OP, _LEN, _CH, n & _U32, time_ns, time_ns, _CDR, time_ns, "
        + "".join(f"{v}, " for v in names)
        + "disturbance_A, applied_A, period_index, drive_state)\n"
        "                    n += 1\n"
        "                    continue\n"
        "            except (ValueError, TypeError, _StructError):\n"
        "                pass\n"
        "            _w._seq_truth = n\n"
        "            _w._batch_records += n - base\n"
        "            n = -1  # the general path keeps the counters meanwhile\n"
        "            _general(t)\n"
        "            n = base = _w._seq_truth\n"
        "    except BaseException:\n"
        "        _w._restage_truth(staged[i + 1 :])\n"
        "        raise\n"
        "    finally:\n"
        "        if n >= 0:\n"
        "            _w._seq_truth = n\n"
        "            _w._batch_records += n - base\n"
    )
    return _define("records", source, writer, pack, length, CH_TRUTH, general)


def _define(
    name: str,
    source: str,
    writer: _Batching,
    pack: Callable[..., bytes],
    length: int,
    channel: int,
    general: Callable[..., None],
) -> Callable[..., None]:
    namespace: dict[str, Any] = {
        "_w": writer,
        "_pack": pack,
        "_general": general,
        "_get_ident": threading.get_ident,
        "_OP": OP_MESSAGE,
        "_LEN": length,
        "_CH": channel,
        "_U32": _U32,
        "_CDR": CDR_HEADER_U32,
        "_StructError": struct.error,
    }
    run_generated(source, "<dob_hil.log.packers generated>", namespace)
    fn: Callable[..., None] = namespace[name]
    fn.source = source  # type: ignore[attr-defined]  # for inspection (tests)
    return fn
