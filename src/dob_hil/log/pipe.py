"""The byte stream from :class:`~dob_hil.log.writer.LogWriter` to its writer process.

A stream of MCAP-framed records (``opcode u8, length u64, body``): data records are complete MCAP
Message records (opcode 0x05: channel, sequence, log time, publish time, CDR payload), exactly as
they go into a chunk, so the writer process copies them in bulk; control records use the private
opcode :data:`OP_CONTROL` (MCAP reserves 0x80-0xFF for private records; these never reach the
file) and their body is UTF-8 JSON with an ``"op"`` key, optionally followed by a NUL byte and a
binary blob (JSON text never contains a raw NUL).

The sequence number of each Message is assigned per channel where the record is made, so a record
that never reached the file (dropped, or lost in a crash) leaves a gap, and a record written twice
a duplicate: :mod:`dob_hil.log.check` finds both.

Control ops, in the order the parent sends them: ``open`` (path, layout, chunking), then any
``attachment`` (JSON name/media_type + blob) and ``metadata`` (name/data), ``sync`` (the process
answers ``ready`` on its status stream), the data records, and ``close`` (the summary).

The writer process answers on its stdout, one JSON object per line: ``{"status": "ready"}``,
``{"status": "closed", "written": {...}}`` or ``{"status": "error", "message": "...",
"written": {...}}`` (``written``: records per kind that reached the file).
"""

from __future__ import annotations

import json
import struct
from typing import Any, Final

OP_CONTROL: Final = 0xF0
RECORD_HEAD: Final = struct.Struct("<BQ")  # opcode, length
OP_OPEN: Final = "open"
OP_ATTACHMENT: Final = "attachment"
OP_METADATA: Final = "metadata"
OP_SYNC: Final = "sync"
OP_CLOSE: Final = "close"

STATUS_READY: Final = "ready"
STATUS_CLOSED: Final = "closed"
STATUS_ERROR: Final = "error"


def control_record(op: str, fields: dict[str, Any], blob: bytes | None = None) -> bytes:
    """One control record: ``{"op": op, **fields}`` as JSON, then NUL and ``blob`` if given."""
    payload = json.dumps({"op": op, **fields}, default=str).encode()
    if blob is not None:
        payload = payload + b"\x00" + blob
    return RECORD_HEAD.pack(OP_CONTROL, len(payload)) + payload


def split_control(payload: bytes) -> tuple[dict[str, Any], bytes | None]:
    """Inverse of :func:`control_record`'s body: (JSON object, blob or None)."""
    text, sep, blob = payload.partition(b"\x00")
    obj = json.loads(text)
    if not isinstance(obj, dict) or not isinstance(obj.get("op"), str):
        raise ValueError(f"control record without an op: {text[:80]!r}")
    return obj, (blob if sep else None)
