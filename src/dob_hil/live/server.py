"""The live-server process: owns the ``foxglove-sdk`` WebSocket server and nothing else.

It advertises the log's channels with the log's own schemas (ros2msg text, CDR messages:
:func:`dob_hil.log.schemas.channel_specs`), so one Foxglove layout works for the live view and for
the MCAP file. It takes the frames :mod:`dob_hil.live.tap` writes to the pipe (``items``, a
``Connection``; each the CDR message the log holds, :mod:`dob_hil.live.packing`) and logs each
on its channel with the record's log time. The design and the run's metadata are served as parameters
(``dob_hil.design``: the design JSON; ``dob_hil.run.<key>``: each run metadata value), which a
viewer can read at any time.

A slow viewer costs nothing here either: the SDK keeps a bounded backlog per client and drops
that client's oldest data messages (``message_backlog_size``).

Status goes back to the parent on ``status`` as tuples: ``("ready", port)``, ``("error",
message)``, and at the end ``("closed", {"served": n, "bad": n})``.
"""

from __future__ import annotations

import signal
import time
from collections.abc import Mapping
from typing import Any

from dob_hil.live.packing import KIND_EVENT, KIND_SAMPLE, KIND_TRUTH, unframe
from dob_hil.log.schemas import CH_EVENT, CH_SAMPLE, CH_TRUTH, LogLayout, channel_specs

LIVE_CHANNELS = (CH_SAMPLE, CH_TRUTH, CH_EVENT)
MESSAGE_BACKLOG = 256  # per client; the SDK drops the oldest data message beyond it


def parameters(design_json: str, run_meta: Mapping[str, str]) -> list[Any]:
    import foxglove

    params = [foxglove.Parameter("dob_hil.design", value=design_json)]
    params += [foxglove.Parameter(f"dob_hil.run.{k}", value=str(v)) for k, v in run_meta.items()]
    return params


def serve(
    items: Any,
    status: Any,
    host: str,
    port: int,
    layout: LogLayout,
    design_json: str,
    run_meta: Mapping[str, str],
    linger_s: float,
) -> None:
    """The process body: serve until the pipe's end, then linger ``linger_s`` and stop.

    A terminal's Ctrl-C reaches the whole process group: the run stops on it and then closes the
    pipe, so this process ignores SIGINT and serves the run's end (its events) first.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        import foxglove
        from foxglove.websocket import Capability, ServerListener

        params = parameters(design_json, run_meta)
        by_name = {p.name: p for p in params}

        class Listener(ServerListener):
            def on_get_parameters(
                self, client: Any, param_names: list[str], request_id: str | None = None
            ) -> list[Any]:
                if not param_names:
                    return params
                return [by_name[n] for n in param_names if n in by_name]

        ctx = foxglove.Context()
        channels: dict[int, Any] = {}
        kinds = {CH_SAMPLE: KIND_SAMPLE, CH_TRUTH: KIND_TRUTH, CH_EVENT: KIND_EVENT}
        for spec in channel_specs(layout):
            if spec.key in LIVE_CHANNELS:
                schema = foxglove.Schema(
                    name=spec.schema_name, encoding=spec.schema_encoding, data=spec.schema_data()
                )
                channels[kinds[spec.key]] = foxglove.Channel(
                    spec.topic, schema=schema, message_encoding=spec.message_encoding, context=ctx
                )
        server = foxglove.start_server(
            name="dob-hil",
            host=host,
            port=port,
            capabilities=[Capability.Parameters],
            server_listener=Listener(),
            context=ctx,
            message_backlog_size=MESSAGE_BACKLOG,
        )
    except Exception as exc:  # the port is taken, the SDK is missing, ...
        status.put(("error", f"{type(exc).__name__}: {exc}"))
        return
    status.put(("ready", server.port))
    served = bad = 0
    try:
        while True:
            try:
                frame = items.recv_bytes()  # bytes only: nothing is deserialised here
            except EOFError:  # the run closed its end: it is over
                break
            try:
                kind, log_time_ns, payload = unframe(frame)
            except ValueError:
                bad += 1
                continue
            channels[kind].log(payload, log_time=log_time_ns)
            served += 1
        if linger_s > 0:
            time.sleep(linger_s)  # let viewers draw the end of the run before the server goes
    finally:
        server.stop()
        status.put(("closed", {"served": served, "bad": bad}))
