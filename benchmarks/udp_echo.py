"""Echo process of the bare udp_multicast round trip (started by the real-time benchmarks).

Answers every PING frame carrying this run's token with a PONG frame of the same data, and
nothing else: python-can's ``udp_multicast`` delivers every frame of every group on its port to
every process (own frames included), so frames are told apart by their 29-bit ids, which the
native drive protocol (11-bit ids) never uses, and by the token. Exits on a frame whose counter
is ``STOP_COUNTER``, or after ``--idle-s`` seconds without a ping.

    python udp_echo.py CHANNEL TOKEN_HEX [--idle-s S]
"""

from __future__ import annotations

import argparse
import struct
import sys

import can

PING_ID = 0x1BE40001
PONG_ID = 0x1BE40002
PAYLOAD = struct.Struct("<4sI")  # token, counter
STOP_COUNTER = 0xFFFFFFFF


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    p.add_argument("channel", help="multicast group, e.g. 239.74.163.20")
    p.add_argument("token", help="8 hex digits: only pings carrying it are answered")
    p.add_argument("--idle-s", type=float, default=20.0, help="exit after this long without a ping")
    args = p.parse_args(argv)
    token = bytes.fromhex(args.token)
    bus = can.Bus(interface="udp_multicast", channel=args.channel, receive_own_messages=False)
    print("ready", flush=True)
    try:
        while True:
            msg = bus.recv(args.idle_s)
            if msg is None:
                print("udp_echo: idle, exiting", file=sys.stderr)
                return 0
            if msg.arbitration_id != PING_ID or not msg.is_extended_id or len(msg.data) != PAYLOAD.size:
                continue
            got_token, counter = PAYLOAD.unpack(msg.data)
            if got_token != token:
                continue
            if counter == STOP_COUNTER:
                return 0
            bus.send(can.Message(arbitration_id=PONG_ID, is_extended_id=True, data=msg.data))
    finally:
        bus.shutdown()


if __name__ == "__main__":
    sys.exit(main())
