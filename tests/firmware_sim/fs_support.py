"""Helpers for the firmware_sim tests: configs built from the paper's scenario, a scripted host."""

from __future__ import annotations

import itertools
import os
import sys
import time
from pathlib import Path
from typing import Any

import can

from dob_hil.config import Config, parse_config
from dob_hil.errors import ProtocolError
from dob_hil.link import protocol
from dob_hil.link.protocol import FrameKind, frame_id

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

REPO_ROOT = Path(__file__).resolve().parents[2]
PAPER_STEP = REPO_ROOT / "src" / "dob_hil" / "scenarios" / "paper-step.toml"

_channels = itertools.count()


def unique_channel() -> str:
    return f"firmware-sim-test-{os.getpid()}-{next(_channels)}"


def paper_data() -> dict[str, Any]:
    return tomllib.loads(PAPER_STEP.read_text(encoding="utf-8"))


def merged_data(**sections: dict[str, Any]) -> dict[str, Any]:
    """The paper-step config data with ``sections`` merged in (``sim={"substeps": 4}`` etc.).

    A value of ``None`` deletes that key (``sim={"disturbance": None}`` removes the disturbance).
    """
    data = paper_data()
    for name, values in sections.items():
        table = data.setdefault(name, {})
        for key, value in values.items():
            if value is None:
                table.pop(key, None)
            else:
                table[key] = value
    return data


def make_config(**sections: dict[str, Any]) -> Config:
    return parse_config(merged_data(**sections))


def toml_text(**sections: dict[str, Any]) -> str:
    """The merged config as TOML text (for the standalone process); validated first."""
    data = merged_data(**sections)
    parse_config(data)
    return dump_toml(data)


def dump_toml(data: dict[str, Any]) -> str:
    """Enough of a TOML writer for config data (tables, arrays of tables, numbers, strings)."""
    lines: list[str] = []

    def value(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v)

    def table(prefix: str, t: dict[str, Any]) -> None:
        scalars = {k: v for k, v in t.items() if not isinstance(v, dict) and not _is_table_array(v)}
        if scalars:
            lines.append(f"[{prefix}]")
            lines.extend(f"{k} = {value(v)}" for k, v in scalars.items())
        for k, v in t.items():
            if isinstance(v, dict):
                table(f"{prefix}.{k}" if prefix else k, v)
            elif _is_table_array(v):
                for item in v:
                    lines.append(f"[[{prefix}.{k}]]")
                    lines.extend(f"{kk} = {value(vv)}" for kk, vv in item.items())

    for k, v in data.items():
        table(k, v)
    return "\n".join(lines) + "\n"


def _is_table_array(v: Any) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


class Host:
    """A scripted host on its own bus end: sends native frames, collects what the drive sends."""

    def __init__(self, bus: can.BusABC, node_id: int = 1) -> None:
        self.bus = bus
        self.node_id = node_id

    def send_raw(self, kind: FrameKind, payload: bytes, node_id: int | None = None) -> None:
        node = self.node_id if node_id is None else node_id
        self.bus.send(can.Message(arbitration_id=frame_id(kind, node), data=payload, is_extended_id=False))

    def control(self, request: protocol.ControlRequest) -> None:
        self.send_raw(FrameKind.CONTROL, protocol.encode_control(protocol.ControlFrame(request)))

    def command(self, current_counts: int, answers_seq: int, enable: bool = True) -> None:
        frame = protocol.CommandFrame(current_counts, answers_seq % protocol.COMMAND_SEQ_MODULO, enable)
        self.send_raw(FrameKind.COMMAND, protocol.encode_command(frame))

    def drain(self, timeout_s: float = 0.0) -> list[protocol.Frame]:
        """Every frame of our node the drive sent so far (waiting up to ``timeout_s`` for the first)."""
        frames: list[protocol.Frame] = []
        msg = self.bus.recv(timeout_s)
        while msg is not None:
            kind, node = protocol.split_id(msg.arbitration_id)
            if node == self.node_id and kind in (FrameKind.FEEDBACK, FrameKind.HEARTBEAT, FrameKind.FAULT):
                frames.append(protocol.decode(msg.arbitration_id, msg.data)[1])
            msg = self.bus.recv(0.0)
        return frames

    def wait_for(self, kind: type[protocol.Frame], timeout_s: float = 5.0) -> list[protocol.Frame]:
        """Frames until (and including) the first of type ``kind``; AssertionError on timeout."""
        deadline = time.monotonic() + timeout_s
        frames: list[protocol.Frame] = []
        while time.monotonic() < deadline:
            msg = self.bus.recv(max(0.0, deadline - time.monotonic()))
            if msg is None:
                break
            try:
                kind_id, node = protocol.split_id(msg.arbitration_id)
            except ProtocolError:
                continue
            if node != self.node_id or kind_id not in (
                FrameKind.FEEDBACK,
                FrameKind.HEARTBEAT,
                FrameKind.FAULT,
            ):
                continue
            frame = protocol.decode(msg.arbitration_id, msg.data)[1]
            frames.append(frame)
            if isinstance(frame, kind):
                return frames
        raise AssertionError(f"no {kind.__name__} within {timeout_s} s; got {frames}")


def feedbacks(frames: list[protocol.Frame]) -> list[protocol.FeedbackFrame]:
    return [f for f in frames if isinstance(f, protocol.FeedbackFrame)]
