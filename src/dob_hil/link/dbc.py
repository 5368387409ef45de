"""The DBC description of the native protocol, shipped as package data.

``native.dbc`` describes the five frames for node 1; :func:`dbc_for_node` rewrites the frame ids
for another node so that a CAN tool (cantools, SavvyCAN, Vector tools) can decode a bus trace of
any drive. Only the ids change: message, signal and node names stay the same.
"""

from __future__ import annotations

import re
from importlib import resources
from importlib.abc import Traversable

from dob_hil.link.protocol import FrameKind, frame_id

DBC_NAME = "native.dbc"
DBC_NODE_ID = 1  # the node the shipped file describes

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


def dbc_for_node(node_id: int) -> str:
    """The DBC text with every frame id rewritten for ``node_id`` (0..127).

    Raises :class:`~dob_hil.errors.ProtocolError` for a node id outside 0..127.
    """
    new_ids = {frame_id(kind, DBC_NODE_ID): frame_id(kind, node_id) for kind in FrameKind}

    def rewrite(match: re.Match[str]) -> str:
        old = int(match.group(2))
        return f"{match.group(1)}{new_ids.get(old, old)}"

    return _ID_STATEMENT.sub(rewrite, dbc_text())
