"""The byte stream from :class:`~dob_hil.log.writer.LogWriter` to its writer process.

A stream of records, each ``<BQI`` (channel u8, log_time_ns u64, payload length u32) followed by
the payload. Channels 1..5 carry message payloads ready for MCAP (CDR with its encapsulation
header, or JSON); channel 0 carries control records whose payload is UTF-8 JSON with an ``"op"``
key, optionally followed by a NUL byte and a binary blob (JSON text never contains a raw NUL).

Control ops, in the order the parent sends them: ``open`` (path, layout, chunking), then any
``attachment`` (JSON name/media_type + blob) and ``metadata`` (name/data), ``sync`` (the process
answers ``ready`` on its status stream), the data records, and ``close`` (the summary).

The writer process answers on its stdout, one JSON object per line: ``{"status": "ready"}``,
``{"status": "closed", "written": {...}}`` or ``{"status": "error", "message": "..."}``.
"""

from __future__ import annotations

import json
from typing import Any, Final

from dob_hil.log.schemas import PIPE_HEADER

CH_CONTROL: Final = 0
OP_OPEN: Final = "open"
OP_ATTACHMENT: Final = "attachment"
OP_METADATA: Final = "metadata"
OP_SYNC: Final = "sync"
OP_CLOSE: Final = "close"

STATUS_READY: Final = "ready"
STATUS_CLOSED: Final = "closed"
STATUS_ERROR: Final = "error"


def control_record(op: str, fields: dict[str, Any], blob: bytes | None = None) -> bytes:
    """One channel-0 record: ``{"op": op, **fields}`` as JSON, then NUL and ``blob`` if given."""
    payload = json.dumps({"op": op, **fields}, default=str).encode()
    if blob is not None:
        payload = payload + b"\x00" + blob
    return PIPE_HEADER.pack(CH_CONTROL, 0, len(payload)) + payload


def split_control(payload: bytes) -> tuple[dict[str, Any], bytes | None]:
    """Inverse of :func:`control_record`'s payload: (JSON object, blob or None)."""
    text, sep, blob = payload.partition(b"\x00")
    obj = json.loads(text)
    if not isinstance(obj, dict) or not isinstance(obj.get("op"), str):
        raise ValueError(f"control record without an op: {text[:80]!r}")
    return obj, (blob if sep else None)
