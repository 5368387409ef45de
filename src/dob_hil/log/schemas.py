"""Message definitions of the log: ros2msg schema text, CDR struct formats and numpy dtypes.

Every ros2msg message of the log has fixed-size fields only, ordered 8-byte first, then 4-byte,
then 1-byte, so that little-endian CDR (encapsulation header ``00 01 00 00``) needs no padding and
every message of a channel has the same length. The writer packs with :mod:`struct`; the reader
parses the schema text stored in the file back into a numpy structured dtype (:func:`parse_msg`,
:func:`msg_dtype`), so it never depends on the writer's code to know the layout.

ROS 2 field names must be lowercase (``[a-z][a-z0-9_]*``): the unit suffix ``_A`` of the Python
API is spelled ``_a`` in the message fields (``u_cmd_a``, ``disturbance_a``).
"""

from __future__ import annotations

import json
import re
import struct
from dataclasses import dataclass
from typing import Final

import numpy as np

from dob_hil.errors import DobHilError

PACKAGE: Final = "dob_hil"
CDR_HEADER: Final = b"\x00\x01\x00\x00"  # CDR_LE encapsulation, options 0
CDR_HEADER_U32: Final = 0x00000100  # the same four bytes read as a little-endian u32
MESSAGE_RECORD_OVERHEAD: Final = 31  # opcode u8, length u64, channel u16, sequence u32, 2 x time u64

TOPIC_SAMPLE: Final = "/dob_hil/sample"
TOPIC_CAN: Final = "/dob_hil/can"
TOPIC_CAN_FD: Final = "/dob_hil/can_fd"
TOPIC_TRUTH: Final = "/dob_hil/truth"
TOPIC_EVENT: Final = "/dob_hil/event"

SCHEMA_SAMPLE: Final = "dob_hil/msg/Sample"
SCHEMA_CAN: Final = "dob_hil/msg/CanFrame"
SCHEMA_CAN_FD: Final = "dob_hil/msg/CanFdFrame"
SCHEMA_TRUTH: Final = "dob_hil/msg/GroundTruth"
SCHEMA_EVENT: Final = "dob_hil/msg/Event"
SCHEMA_EVENT_JSON_V1: Final = "dob_hil/Event"  # logs of format version 1: JSON events (still read)

CAN_DATA_BYTES: Final = 8
CAN_FD_DATA_BYTES: Final = 64

# Sample.flags bits
FLAG_SATURATED: Final = 1 << 0
FLAG_OVERRUN: Final = 1 << 1
FLAG_FEEDBACK_MISSING: Final = 1 << 2  # feedback missing, substituted by the missing-feedback policy
FLAG_DOB_ON: Final = 1 << 3

# CanFrame.flags bits
CAN_FLAG_EXTENDED: Final = 1 << 0
CAN_FLAG_ERROR: Final = 1 << 1
CAN_FLAG_REMOTE: Final = 1 << 2
CAN_FLAG_FD: Final = 1 << 3
CAN_FLAG_BRS: Final = 1 << 4  # CAN FD bit rate switch
CAN_FLAG_ESI: Final = 1 << 5  # CAN FD error state indicator
CAN_RX: Final = 0
CAN_TX: Final = 1

EVENT_LEVELS: Final = ("info", "warning", "error")


class SchemaError(DobHilError):
    """A ros2msg schema text that the log cannot use (unknown type, variable-length field)."""


@dataclass(frozen=True, slots=True)
class PrimitiveType:
    name: str  # ros2msg name
    struct_char: str
    numpy: str  # little-endian numpy type string
    size: int


PRIMITIVES: Final[dict[str, PrimitiveType]] = {
    p.name: p
    for p in (
        PrimitiveType("float64", "d", "<f8", 8),
        PrimitiveType("int64", "q", "<i8", 8),
        PrimitiveType("uint64", "Q", "<u8", 8),
        PrimitiveType("float32", "f", "<f4", 4),
        PrimitiveType("int32", "i", "<i4", 4),
        PrimitiveType("uint32", "I", "<u4", 4),
        PrimitiveType("int16", "h", "<i2", 2),
        PrimitiveType("uint16", "H", "<u2", 2),
        PrimitiveType("int8", "b", "<i1", 1),
        PrimitiveType("uint8", "B", "<u1", 1),
        PrimitiveType("byte", "B", "<u1", 1),
        PrimitiveType("char", "B", "<u1", 1),
        PrimitiveType("bool", "?", "?", 1),
    )
}


@dataclass(frozen=True, slots=True)
class Field:
    """One message field: ``type name`` (count None) or ``type[count] name``."""

    name: str
    type: str
    count: int | None = None
    comment: str = ""

    @property
    def primitive(self) -> PrimitiveType:
        return PRIMITIVES[self.type]

    @property
    def n_values(self) -> int:
        return 1 if self.count is None else self.count

    @property
    def size(self) -> int:
        return self.primitive.size * self.n_values


@dataclass(frozen=True, slots=True)
class LogLayout:
    """Dimensions that fix every array size of the log's messages.

    ``n_states``: augmented controller state count (x_ref, x_hat, x_bar); ``n_inputs``: m (currents);
    ``n_outputs``: p (measured outputs, encoders); ``n_plant_states``: the simulated plant's states.
    """

    n_states: int
    n_inputs: int
    n_outputs: int
    n_plant_states: int

    def __post_init__(self) -> None:
        for name in ("n_states", "n_inputs", "n_outputs", "n_plant_states"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or not 1 <= value <= 64:
                raise SchemaError(f"LogLayout.{name}: expected an integer in 1..64, got {value!r}")

    def as_metadata(self) -> dict[str, str]:
        return {
            "n_states": str(self.n_states),
            "n_inputs": str(self.n_inputs),
            "n_outputs": str(self.n_outputs),
            "n_plant_states": str(self.n_plant_states),
        }


def sample_fields(layout: LogLayout) -> tuple[Field, ...]:
    n, m, p = layout.n_states, layout.n_inputs, layout.n_outputs
    return (
        Field("time_ns", "uint64", None, "sample instant (scheduled deadline; lockstep k * period_ns)"),
        Field("rx_time_ns", "uint64", None, "feedback receive time"),
        Field("tx_time_ns", "uint64", None, "command send time"),
        Field("lateness_ns", "int64", None, "rx_time_ns - time_ns"),
        Field("counts", "int64", p, "unwrapped encoder counts"),
        Field("position", "float64", p, "measured output y"),
        Field("x_ref", "float64", n, "reference state"),
        Field("x_hat", "float64", n, "corrected state estimate"),
        Field("x_bar", "float64", n, "predicted state estimate"),
        Field("u_fb", "float64", m, "state feedback current, A"),
        Field("u_dist", "float64", m, "disturbance compensation current, A"),
        Field("u_cmd_a", "float64", m, "commanded current before limit/quantization, A"),
        Field("u_applied_a", "float64", m, "command sent, A"),
        Field("seq", "uint32", None, "host sample index k"),
        Field("compute_ns", "uint32", None, "controller step time"),
        Field("dac_counts", "int32", m, "command sent, DAC counts"),
        Field("feedback_seq", "uint8", None, "the drive's feedback sequence"),
        Field("flags", "uint8", None, "bit0 saturated, bit1 overrun, bit2 feedback missing, bit3 dob on"),
    )


def can_fields(data_bytes: int = CAN_DATA_BYTES) -> tuple[Field, ...]:
    return (
        Field("timestamp_ns", "uint64", None, "bus timestamp"),
        Field("arbitration_id", "uint32"),
        Field("direction", "uint8", None, "0 rx, 1 tx"),
        Field("dlc", "uint8", None, "data length in bytes"),
        Field(
            "flags",
            "uint8",
            None,
            "bit0 extended, bit1 error frame, bit2 remote, bit3 fd, bit4 brs, bit5 esi",
        ),
        Field("data", "uint8", data_bytes, "zero padded"),
    )


def truth_fields(layout: LogLayout) -> tuple[Field, ...]:
    m = layout.n_inputs
    return (
        Field("time_ns", "uint64", None, "drive time of the period"),
        Field("state", "float64", layout.n_plant_states, "plant state"),
        Field("disturbance_a", "float64", m, "injected disturbance current, A"),
        Field("applied_current_a", "float64", m, "current applied to the plant, A"),
        Field("period_index", "uint32"),
        Field("drive_state", "uint8", None, "0 disabled, 1 enabled, 2 fault"),
    )


def msg_text(fields: tuple[Field, ...]) -> str:
    """The ros2msg schema text of ``fields`` (one ``type[N] name  # comment`` per line)."""
    lines = []
    for f in fields:
        type_text = f.type if f.count is None else f"{f.type}[{f.count}]"
        line = f"{type_text} {f.name}"
        if f.comment:
            line = f"{line}  # {f.comment}"
        lines.append(line)
    return "\n".join(lines) + "\n"


_FIELD_LINE = re.compile(
    r"^(?P<type>[A-Za-z_][A-Za-z0-9_/]*)(?P<array>\[(?P<count>[^\]]*)\])?\s+(?P<name>\S+)$"
)


def parse_msg(text: str) -> tuple[Field, ...]:
    """Parse a ros2msg text of primitive fields and fixed-size arrays.

    Raises :class:`SchemaError` naming the line for strings, nested types, variable-length
    arrays or default values, which have no fixed CDR size.
    """
    fields: list[Field] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        if line.startswith("===="):  # start of a dependency definition: none in our schemas
            break
        if "=" in line:  # a constant: occupies no bytes in the message
            continue
        match = _FIELD_LINE.match(line)
        if match is None:
            raise SchemaError(f"schema line {lineno}: cannot parse {raw.strip()!r} as a fixed-size field")
        ftype = match["type"]
        if ftype not in PRIMITIVES:
            raise SchemaError(f"schema line {lineno}: type {ftype!r} is not a fixed-size primitive")
        count: int | None = None
        if match["array"] is not None:
            if not match["count"] or not match["count"].isdigit():
                raise SchemaError(f"schema line {lineno}: array {raw.strip()!r} is not fixed-size")
            count = int(match["count"])
        fields.append(Field(match["name"], ftype, count))
    if not fields:
        raise SchemaError("schema has no fields")
    return tuple(fields)


def cdr_offsets(fields: tuple[Field, ...]) -> tuple[list[int], int]:
    """Byte offset of each field after the 4-byte encapsulation header, and the body size.

    CDR aligns every primitive to its own size (at most 8) relative to the start of the body.
    """
    offsets = []
    pos = 0
    for f in fields:
        align = min(f.primitive.size, 8)
        pos = (pos + align - 1) // align * align
        offsets.append(pos)
        pos += f.size
    return offsets, pos


def msg_dtype(fields: tuple[Field, ...]) -> np.dtype[np.void]:
    """numpy structured dtype of the CDR body (header excluded); arrays become subarrays."""
    offsets, size = cdr_offsets(fields)
    formats: list[object] = [
        f.primitive.numpy if f.count is None else (f.primitive.numpy, (f.count,)) for f in fields
    ]
    return np.dtype(
        {"names": [f.name for f in fields], "formats": formats, "offsets": offsets, "itemsize": size}
    )


def struct_body_format(fields: tuple[Field, ...]) -> str:
    """struct format (no byte-order prefix) of a padding-free CDR body; uint8 arrays as ``Ns``."""
    _, size = cdr_offsets(fields)
    if size != sum(f.size for f in fields):
        raise SchemaError("message fields need CDR padding: order them 8-byte first, then 4, then 1")
    parts = []
    for f in fields:
        if f.count is None:
            parts.append(f.primitive.struct_char)
        elif f.type in ("uint8", "byte", "char"):
            parts.append(f"{f.count}s")
        else:
            parts.append(f"{f.count}{f.primitive.struct_char}")
    return "".join(parts)


def body_size(fields: tuple[Field, ...]) -> int:
    return cdr_offsets(fields)[1]


EVENT_MSG_TEXT: Final = """\
uint64 time_ns  # event time, ns (the loop's clock)
string level  # info, warning or error
string kind  # machine-readable kind, e.g. drive_fault, log_overflow
string message
string data  # a JSON object: the event's details
"""


def encode_event_cdr(time_ns: int, level: str, kind: str, message: str, data_json: str) -> bytes:
    """The CDR payload (encapsulation header included) of one ``dob_hil/msg/Event``.

    CDR: ``uint64`` at offset 0 of the body, then each string as a ``uint32`` length (bytes + NUL)
    aligned to 4, its UTF-8 bytes and a NUL.
    """
    out = bytearray(CDR_HEADER)
    out += struct.pack("<Q", time_ns)
    for text in (level, kind, message, data_json):
        raw = text.encode("utf-8", errors="replace")
        body_pos = len(out) - 4
        out += bytes(-body_pos % 4)
        out += struct.pack("<I", len(raw) + 1)
        out += raw
        out += b"\x00"
    return bytes(out)


def decode_event_cdr(payload: bytes | bytearray | memoryview) -> dict[str, object]:
    """Inverse of :func:`encode_event_cdr`: ``{"time_ns", "level", "kind", "message", "data"}``.

    Raises ValueError for a payload that is not such a message (``data`` must be a JSON object).
    """
    buf = bytes(payload)
    if len(buf) < 12 or buf[:4] != CDR_HEADER:
        raise ValueError("not a little-endian CDR message")
    body = memoryview(buf)[4:]
    (time_ns,) = struct.unpack_from("<Q", body, 0)
    pos = 8
    texts: list[str] = []
    for _ in range(4):
        pos += -pos % 4
        if pos + 4 > len(body):
            raise ValueError("string field runs past the message end")
        (length,) = struct.unpack_from("<I", body, pos)
        pos += 4
        if length < 1 or pos + length > len(body) or body[pos + length - 1] != 0:
            raise ValueError("string field of a bad length")
        texts.append(bytes(body[pos : pos + length - 1]).decode("utf-8", errors="replace"))
        pos += length
    data = json.loads(texts[3])
    if not isinstance(data, dict):
        raise ValueError("event data is not a JSON object")
    return {"time_ns": int(time_ns), "level": texts[0], "kind": texts[1], "message": texts[2], "data": data}


@dataclass(frozen=True, slots=True)
class ChannelSpec:
    """One channel of the log: its topic, schema and encodings. ``fields`` is None for JSON.

    ``block``: the channel's messages are blocks (``[run] log_layout = "blocks"``): each holds a run
    of consecutive records of ``fields`` as one sequence (:func:`block_msg_text`)."""

    key: int  # channel number on the writer pipe, and the MCAP channel id the writer assigns
    topic: str
    schema_name: str
    schema_encoding: str
    message_encoding: str
    fields: tuple[Field, ...] | None  # None: the variable-length event message
    block: bool = False

    def schema_data(self) -> bytes:
        if self.fields is None:
            return EVENT_MSG_TEXT.encode()
        if self.block:
            return block_msg_text(self.schema_name.removesuffix(BLOCK_SUFFIX), self.fields).encode()
        return msg_text(self.fields).encode()


# ------------------------------------------------------------------ the block layout
# A block message holds a run of consecutive records of one channel as a ros2msg sequence of the
# per-record message: CDR ``uint32 count``, 4 bytes of padding (the records start with a uint64),
# then the records, each padded to a multiple of 8 bytes (CDR aligns each record's first uint64).
# The Message record's sequence number is its first record's, its log time its first record's
# and its publish time its last record's; a record's own log time is its first field.
BLOCK_SUFFIX: Final = "Block"
BLOCK_FIELD: Final = "records"
BLOCK_SEPARATOR: Final = "=" * 80
BLOCK_HEAD_BYTES: Final = 8  # count u32 + padding, after the CDR encapsulation header


def block_stride(fields: tuple[Field, ...]) -> int:
    """Bytes per record inside a block: the record's body padded to a multiple of 8."""
    return (body_size(fields) + 7) // 8 * 8


def block_msg_text(record_schema_name: str, fields: tuple[Field, ...]) -> str:
    """The ros2msg text of a block of ``record_schema_name`` records (``dob_hil/msg/Sample``),
    with the record's definition as a dependency, as rosbag2 writes nested types."""
    package, _, name = record_schema_name.partition("/msg/")
    return (
        f"# consecutive {name} records of this channel, in order (a block-layout log)\n"
        f"{package}/{name}[] {BLOCK_FIELD}\n{BLOCK_SEPARATOR}\nMSG: {package}/{name}\n{msg_text(fields)}"
    )


_BLOCK_FIELD_LINE: Final = re.compile(r"(?P<type>[A-Za-z_][A-Za-z0-9_]*/[A-Za-z_][A-Za-z0-9_]*)\[\]\s+\S+")


def parse_block_msg(text: str) -> tuple[Field, ...]:
    """The record fields of a block schema text (:func:`block_msg_text`); SchemaError if it is not one."""
    head, sep, rest = text.partition(BLOCK_SEPARATOR)
    if not sep:
        raise SchemaError("block schema without the record's definition")
    lines = [line.split("#", 1)[0].strip() for line in head.splitlines()]
    lines = [line for line in lines if line]
    match = _BLOCK_FIELD_LINE.fullmatch(lines[0]) if len(lines) == 1 else None
    if match is None:
        raise SchemaError("block schema: expected one sequence field of the record type")
    body = rest.lstrip("\n")
    first, _, definition = body.partition("\n")
    if first.strip() != f"MSG: {match['type']}":
        raise SchemaError(f"block schema: no definition of {match['type']!r}")
    return parse_msg(definition)


CH_SAMPLE: Final = 1
CH_CAN: Final = 2
CH_CAN_FD: Final = 3
CH_TRUTH: Final = 4
CH_EVENT: Final = 5


# the writer's summary metadata: records written per channel (exact counts of a block channel)
WRITTEN_KEYS: Final = {
    CH_SAMPLE: "samples_written",
    CH_CAN: "frames_written",
    CH_CAN_FD: "fd_frames_written",
    CH_TRUTH: "truth_written",
    CH_EVENT: "events_written",
}
MESSAGE_LAYOUTS: Final = ("samples", "blocks")  # [run] log_layout: one message per record, or blocks


def channel_specs(layout: LogLayout, message_layout: str = "samples") -> tuple[ChannelSpec, ...]:
    """The log's channels, in registration order (so the MCAP channel ids are 1..5).

    ``message_layout`` "blocks": the fixed-size channels carry blocks of records (their schema
    names end in ``Block``); events stay one message each."""
    if message_layout not in MESSAGE_LAYOUTS:
        raise SchemaError(f"log layout: expected one of {', '.join(MESSAGE_LAYOUTS)}, got {message_layout!r}")
    b = message_layout == "blocks"
    s = BLOCK_SUFFIX if b else ""
    fixed = (
        (CH_SAMPLE, TOPIC_SAMPLE, SCHEMA_SAMPLE, sample_fields(layout)),
        (CH_CAN, TOPIC_CAN, SCHEMA_CAN, can_fields(CAN_DATA_BYTES)),
        (CH_CAN_FD, TOPIC_CAN_FD, SCHEMA_CAN_FD, can_fields(CAN_FD_DATA_BYTES)),
        (CH_TRUTH, TOPIC_TRUTH, SCHEMA_TRUTH, truth_fields(layout)),
    )
    return (
        *(
            ChannelSpec(key, topic, name + s, "ros2msg", "cdr", fields, b)
            for key, topic, name, fields in fixed
        ),
        ChannelSpec(CH_EVENT, TOPIC_EVENT, SCHEMA_EVENT, "ros2msg", "cdr", None),
    )


OP_MESSAGE: Final = 0x05
# An MCAP Message record's header: opcode, record length, channel, sequence, log time, publish time.
MESSAGE_HEADER: Final = struct.Struct("<BQHIQQ")


def record_struct(fields: tuple[Field, ...]) -> struct.Struct:
    """One MCAP Message record of a fixed-size CDR message: header, CDR encapsulation, body."""
    return struct.Struct("<BQHIQQI" + struct_body_format(fields))


def record_length(fields: tuple[Field, ...]) -> int:
    """The Message record's length field (everything after opcode and length) for ``fields``."""
    return MESSAGE_RECORD_OVERHEAD - 9 + 4 + body_size(fields)
