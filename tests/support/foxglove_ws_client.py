"""A minimal Foxglove WebSocket protocol client for the live-view tests.

The SDK's server speaks the protocol under the subprotocol name ``foxglove.sdk.v1`` (the same
messages as ``foxglove.websocket.v1``, which the client also offers).

Implements what a viewer does: read ``serverInfo`` and ``advertise``, ``subscribe`` to channels,
take ``messageData`` binary messages (opcode 1: subscription id u32, log time u64, payload), and
``getParameters``. Built on the ``websockets`` package's synchronous client.
"""

from __future__ import annotations

import contextlib
import json
import struct
import time
from dataclasses import dataclass
from typing import Any

from websockets.sync.client import ClientConnection, connect

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]  # the SDK server speaks the first
OP_MESSAGE_DATA = 0x01
_DATA_HEAD = struct.Struct("<BIQ")


@dataclass(frozen=True)
class Received:
    topic: str
    log_time_ns: int
    payload: bytes


class FoxgloveClient:
    def __init__(self, url: str, open_timeout_s: float = 30.0) -> None:
        self._stack = contextlib.ExitStack()
        self.ws: ClientConnection = self._stack.enter_context(
            connect(url, subprotocols=SUBPROTOCOLS, open_timeout=open_timeout_s)  # type: ignore[arg-type]
        )
        self.server_info: dict[str, Any] | None = None
        self.channels: dict[int, dict[str, Any]] = {}  # advertised, by channel id
        self.topics_by_sub: dict[int, str] = {}
        self.messages: list[Received] = []
        self.texts: list[dict[str, Any]] = []

    def close(self) -> None:
        self._stack.close()

    def _take(self, raw: str | bytes) -> None:
        if isinstance(raw, bytes):
            op, sub_id, log_time_ns = _DATA_HEAD.unpack_from(raw)
            if op == OP_MESSAGE_DATA:
                self.messages.append(
                    Received(self.topics_by_sub[sub_id], log_time_ns, raw[_DATA_HEAD.size :])
                )
            return
        msg = json.loads(raw)
        if msg.get("op") == "serverInfo":
            self.server_info = msg
        elif msg.get("op") == "advertise":
            for ch in msg["channels"]:
                self.channels[int(ch["id"])] = ch
        self.texts.append(msg)

    def pump(self, timeout_s: float) -> bool:
        """Read one message (False: none within ``timeout_s``, or the server closed)."""
        try:
            raw = self.ws.recv(timeout=timeout_s)
        except TimeoutError:
            return False
        except Exception:  # closed by the server at the end of the run
            return False
        self._take(raw)
        return True

    def wait_for_topics(self, topics: set[str], timeout_s: float) -> dict[str, dict[str, Any]]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            have = {ch["topic"]: ch for ch in self.channels.values()}
            if topics <= set(have):
                return have
            self.pump(0.5)
        raise AssertionError(
            f"not advertised within {timeout_s} s: {topics - {c['topic'] for c in self.channels.values()}}"
        )

    def subscribe(self, topics: set[str]) -> None:
        subs = []
        for ch_id, ch in self.channels.items():
            if ch["topic"] in topics:
                sub_id = len(self.topics_by_sub) + 1
                self.topics_by_sub[sub_id] = ch["topic"]
                subs.append({"id": sub_id, "channelId": ch_id})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def get_parameters(self, names: list[str], timeout_s: float) -> list[dict[str, Any]]:
        self.ws.send(json.dumps({"op": "getParameters", "parameterNames": names, "id": "q1"}))
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for msg in self.texts:
                if msg.get("op") == "parameterValues" and msg.get("id") == "q1":
                    return list(msg["parameters"])
            self.pump(0.5)
        raise AssertionError(f"no parameterValues within {timeout_s} s")
