"""The live items as bytes: the log's CDR payloads, framed for the pipe to the live server.

The tap packs each forwarded record into the very CDR message the MCAP log holds (same
``struct`` layout as :mod:`dob_hil.log.writer`), so the live process only unframes bytes and
hands them to the SDK: nothing is deserialised across the process boundary. A frame is
``kind u8, log time u64, payload`` (little-endian).
"""

from __future__ import annotations

import struct
from typing import Any, Final

from dob_hil.log.schemas import (
    CDR_HEADER,
    CH_SAMPLE,
    CH_TRUTH,
    LogLayout,
    channel_specs,
    encode_event_cdr,
    struct_body_format,
)

KIND_SAMPLE: Final = 1
KIND_TRUTH: Final = 2
KIND_EVENT: Final = 3
FRAME_HEAD: Final = struct.Struct("<BQ")


def _flatten(args: tuple[Any, ...]) -> list[Any]:
    out: list[Any] = []
    for a in args:
        if isinstance(a, (tuple, list)):
            out.extend(a)
        else:
            out.append(a)
    return out


class Packer:
    """The log's CDR payload (encapsulation header included) of a forwarded record."""

    def __init__(self, layout: LogLayout) -> None:
        specs = {s.key: s for s in channel_specs(layout)}
        self._structs: dict[int, struct.Struct] = {}
        for kind, key in ((KIND_SAMPLE, CH_SAMPLE), (KIND_TRUTH, CH_TRUTH)):
            fields = specs[key].fields
            assert fields is not None
            self._structs[kind] = struct.Struct("<" + struct_body_format(fields))

    def pack(self, kind: int, args: tuple[Any, ...]) -> tuple[int, bytes]:
        """(log time, payload); raises ValueError for an item that does not pack."""
        if kind == KIND_EVENT:
            time_ns, level, ev_kind, message, data_json = args
            return int(time_ns), encode_event_cdr(int(time_ns), level, ev_kind, message, data_json)
        s = self._structs.get(kind)
        if s is None:
            raise ValueError(f"unknown live item kind {kind!r}")
        try:
            return int(args[0]), CDR_HEADER + s.pack(*_flatten(args))
        except (struct.error, TypeError, IndexError) as exc:
            raise ValueError(f"live {kind} item does not pack: {exc}") from exc

    def frame(self, kind: int, args: tuple[Any, ...]) -> bytes:
        """The pipe frame of a record: kind, log time, CDR payload."""
        log_time_ns, payload = self.pack(kind, args)
        return FRAME_HEAD.pack(kind, log_time_ns) + payload


def unframe(frame: bytes) -> tuple[int, int, bytes]:
    """(kind, log time, payload) of a frame; ValueError for a frame too short or of no kind."""
    if len(frame) < FRAME_HEAD.size:
        raise ValueError(f"live frame of {len(frame)} bytes")
    kind, log_time_ns = FRAME_HEAD.unpack_from(frame)
    if kind not in (KIND_SAMPLE, KIND_TRUTH, KIND_EVENT):
        raise ValueError(f"live frame of unknown kind {kind}")
    return kind, log_time_ns, frame[FRAME_HEAD.size :]
