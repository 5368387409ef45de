"""Message schemas: generated text, CDR layout (no padding), and an independent parser's view."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap_ros2._dynamic import generate_dynamic

from dob_hil.log.schemas import (
    CDR_HEADER,
    EVENT_MSG_TEXT,
    SCHEMA_EVENT,
    LogLayout,
    SchemaError,
    can_fields,
    cdr_offsets,
    channel_specs,
    decode_event_cdr,
    encode_event_cdr,
    msg_dtype,
    msg_text,
    parse_msg,
    record_struct,
    sample_fields,
    struct_body_format,
)

layouts = st.builds(
    LogLayout,
    st.integers(1, 8),
    st.integers(1, 4),
    st.integers(1, 4),
    st.integers(1, 8),
)


def test_paper_sample_is_146_bytes_of_cdr() -> None:
    fields = sample_fields(LogLayout(2, 1, 1, 2))
    assert len(CDR_HEADER) + struct.calcsize("<" + struct_body_format(fields)) == 146
    assert msg_dtype(fields).itemsize == 142


@given(layouts)
@settings(max_examples=40, deadline=None)
def test_every_channel_needs_no_padding_and_parses_back(layout: LogLayout) -> None:
    for spec in channel_specs(layout):
        if spec.fields is None:
            continue
        offsets, size = cdr_offsets(spec.fields)
        assert size == sum(f.size for f in spec.fields)  # no padding
        for f, off in zip(spec.fields, offsets, strict=True):
            assert off % f.primitive.size == 0  # every field aligned as CDR requires
        parsed = parse_msg(msg_text(spec.fields))
        assert [(f.name, f.type, f.count) for f in parsed] == [(f.name, f.type, f.count) for f in spec.fields]
        assert msg_dtype(parsed) == msg_dtype(spec.fields)
        assert struct.calcsize("<" + struct_body_format(spec.fields)) == msg_dtype(parsed).itemsize


@given(layouts, st.randoms(use_true_random=False))
@settings(max_examples=25, deadline=None)
def test_mcap_ros2_decodes_our_packing_like_numpy(layout: LogLayout, rnd: object) -> None:
    """Pack random values with the writer's struct; decode with mcap_ros2 and with the dtype."""
    import random

    assert isinstance(rnd, random.Random)
    fields = sample_fields(layout)
    values: list[object] = []
    for f in fields:
        n = f.n_values
        if f.type == "float64":
            vals: list[object] = [rnd.uniform(-1e6, 1e6) for _ in range(n)]
        elif f.type.startswith("uint"):
            vals = [rnd.randrange(0, 2 ** (8 * f.primitive.size)) for _ in range(n)]
        else:
            bits = 8 * f.primitive.size
            vals = [rnd.randrange(-(2 ** (bits - 1)), 2 ** (bits - 1)) for _ in range(n)]
        values.extend(vals)
    packed = record_struct(fields).pack(5, 0, 1, 0, 0, 0, 0x100, *values)[31:]
    assert packed[:4] == CDR_HEADER
    decoded = generate_dynamic("dob_hil/msg/Sample", msg_text(fields))["dob_hil/msg/Sample"](packed)
    row = np.frombuffer(packed[4:], dtype=msg_dtype(fields))[0]
    flat: list[object] = []
    for f in fields:
        ours = row[f.name]
        theirs = getattr(decoded, f.name)
        if f.count is None:
            assert ours == theirs
            flat.append(theirs)
        else:
            assert list(ours) == list(theirs)
            flat.extend(theirs)
    assert flat == values


def test_can_frame_is_23_bytes_and_data_zero_padded() -> None:
    fields = can_fields()
    assert msg_dtype(fields).itemsize == 23
    packed = record_struct(fields).pack(5, 49, 2, 0, 5, 5, 0x100, 5, 0x181, 0, 3, 0, b"\x01\x02\x03")[31:]
    decoded = generate_dynamic("dob_hil/msg/CanFrame", msg_text(fields))["dob_hil/msg/CanFrame"](packed)
    assert list(decoded.data) == [1, 2, 3, 0, 0, 0, 0, 0]


@pytest.mark.parametrize(
    "text",
    [
        "string name\n",
        "float64[] x\n",
        "float64[<=3] x\n",
        "geometry_msgs/Point p\n",
        "float64 x 1.0\n",
        "\n",
    ],
)
def test_parse_rejects_what_has_no_fixed_size(text: str) -> None:
    with pytest.raises(SchemaError):
        parse_msg(text)


def test_constants_and_comments_take_no_bytes() -> None:
    fields = parse_msg("# header\nuint8 FLAG_A=1\nuint64 t  # time\nuint8[2] d\n")
    assert [(f.name, f.count) for f in fields] == [("t", None), ("d", 2)]


@pytest.mark.parametrize("bad", [0, -1, 65, 1.5, True])
def test_layout_rejects_bad_dimensions(bad: object) -> None:
    with pytest.raises(SchemaError, match="n_inputs"):
        LogLayout(2, bad, 1, 2)  # type: ignore[arg-type]


@given(
    st.integers(0, 2**64 - 1),
    st.sampled_from(["info", "warning", "error"]),
    st.text(max_size=40),
    st.text(max_size=80),
    st.dictionaries(st.text(max_size=8), st.integers(-(2**63), 2**63) | st.text(max_size=8), max_size=4),
)
@settings(max_examples=50, deadline=None)
def test_event_cdr_round_trips_and_mcap_ros2_decodes_it(
    time_ns: int, level: str, kind: str, message: str, data: dict[str, object]
) -> None:
    """The event message is ros2msg/cdr like every channel: mcap_ros2 decodes our bytes."""
    text = json.dumps(data)
    packed = encode_event_cdr(time_ns, level, kind, message, text)
    ours = decode_event_cdr(packed)
    assert ours == {"time_ns": time_ns, "level": level, "kind": kind,
                    "message": message.encode("utf-8", "replace").decode(), "data": data}  # fmt: skip
    theirs = generate_dynamic(SCHEMA_EVENT, EVENT_MSG_TEXT)[SCHEMA_EVENT](packed)
    assert (theirs.time_ns, theirs.level, theirs.kind) == (time_ns, level, ours["kind"])
    assert theirs.message == ours["message"] and json.loads(theirs.data) == data


def test_every_channel_schema_is_named_dob_hil_msg() -> None:
    for spec in channel_specs(LogLayout(2, 1, 1, 2)):
        assert spec.schema_name.startswith("dob_hil/msg/") and spec.schema_encoding == "ros2msg"
