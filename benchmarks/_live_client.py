"""A Foxglove WebSocket viewer for bench_live.py, in its own process (as a real viewer would be).

    python benchmarks/_live_client.py PORT [--slow]

Connects, subscribes to every advertised channel, prints ``subscribed`` and then, until the server
goes: reads every message (a fast viewer) or, with ``--slow``, never reads again (a stalled viewer
whose socket buffers fill). Prints ``received N`` at the end.
"""

from __future__ import annotations

import json
import sys
import time

from websockets.sync.client import connect

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


def main() -> None:
    port = int(sys.argv[1])
    slow = "--slow" in sys.argv[2:]
    received = 0
    with connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, open_timeout=60) as ws:  # type: ignore[arg-type]
        channels: dict[int, str] = {}
        while len(channels) < 3:
            msg = ws.recv(timeout=60)
            if isinstance(msg, str):
                obj = json.loads(msg)
                if obj.get("op") == "advertise":
                    channels.update({int(c["id"]): c["topic"] for c in obj["channels"]})
        subs = [{"id": i + 1, "channelId": ch} for i, ch in enumerate(sorted(channels))]
        ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        print("subscribed", flush=True)
        if slow:
            while True:
                time.sleep(3600)
        try:
            while True:
                msg = ws.recv(timeout=600)
                received += isinstance(msg, bytes)
        except Exception:  # the server went at the end of the run
            pass
    print(f"received {received}", flush=True)


if __name__ == "__main__":
    main()
