"""The DBC description of the native protocol, shipped as package data.

``native.dbc`` describes the five frames of protocol version 2 for node 1, with their send
types and cycle times (``GenMsgSendType``; ``GenMsgCycleTime`` in ms for the 100 ms HEARTBEAT,
``GenMsgCycleTimeUs`` for the per-period FEEDBACK and COMMAND, 300 us in the shipped scenarios,
since a period below 1 ms has no integer millisecond) and the database attributes
``ProtocolVersion`` and ``HeartbeatPeriodMs``. :func:`dbc_for_node` rewrites the frame ids for
another node (and the cycle time for another period) so that a CAN tool (cantools, SavvyCAN,
Vector tools) can decode a bus trace of any drive. Message, signal and node names stay the same.
"""

from __future__ import annotations

import re
from importlib import resources
from importlib.abc import Traversable

from dob_hil.errors import ProtocolError
from dob_hil.link.protocol import FrameKind, frame_id

DBC_NAME = "native.dbc"
DBC_NODE_ID = 1  # the node the shipped file describes
DBC_PERIOD_US = 300  # the control period the shipped file's cycle times describe
_CYCLE_US = re.compile(r'^(BA_ "GenMsgCycleTimeUs" BO_ \d+ )(\d+);', re.MULTILINE)

# Every DBC statement that names a message by its id, with the id as the second group.
_ID_STATEMENT = re.compile(
    r'^(BO_ |CM_ BO_ |CM_ SG_ |VAL_ |BO_TX_BU_ |SIG_VALTYPE_ |BA_ "[^"]*" BO_ |BA_ "[^"]*" SG_ )(\d+)\b',
    re.MULTILINE,
)


def dbc_resource() -> Traversable:
    """The shipped ``native.dbc`` (use ``importlib.resources.as_file`` for a file system path)."""
    return resources.files("dob_hil.link") / DBC_NAME


def dbc_text() -> str:
    """The text of the shipped DBC (node 1)."""
    return dbc_resource().read_text(encoding="utf-8")


def dbc_for_node(node_id: int, *, period_us: int = DBC_PERIOD_US) -> str:
    """The DBC text with every frame id rewritten for ``node_id`` (0..15) and the cyclic frames'
    ``GenMsgCycleTimeUs`` for a control period of ``period_us``.

    Raises :class:`~dob_hil.errors.ProtocolError` for a node id outside 0..15 or a period < 1 us.
    """
    if isinstance(period_us, bool) or not isinstance(period_us, int) or not 1 <= period_us <= 65_535_000:
        raise ProtocolError(f"period_us: must be an integer 1..65535000, got {period_us!r}")
    new_ids = {frame_id(kind, DBC_NODE_ID): frame_id(kind, node_id) for kind in FrameKind}

    def rewrite(match: re.Match[str]) -> str:
        old = int(match.group(2))
        return f"{match.group(1)}{new_ids.get(old, old)}"

    text = _ID_STATEMENT.sub(rewrite, dbc_text())
    return _CYCLE_US.sub(lambda m: f"{m.group(1)}{period_us};", text)
