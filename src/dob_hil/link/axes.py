"""Several axes on one drive bus: which node drives which input and output.

A plant with N > 1 inputs runs on N axes (drive nodes) of one bus: axis i is plant input i (its
current) and plant output i (its encoder), so the plant must be square (``n_inputs ==
n_outputs``). ``drive.node_ids`` names the node of each axis (default ``node_id + i``). Both the
host's link (:mod:`dob_hil.link.native_axes`) and the simulated drive (:mod:`firmware_sim.axes`)
take their nodes from here, so they agree on the mapping.
"""

from __future__ import annotations

from dob_hil.config import DriveConfig, PlantConfig
from dob_hil.errors import ConfigError
from dob_hil.link.protocol import NODE_ID_MAX


def check_square(plant: PlantConfig) -> int:
    """The number of axes of ``plant`` (one per input and output); ConfigError if not square."""
    if plant.n_inputs != plant.n_outputs:
        raise ConfigError(
            "plant.C",
            f"a drive runs one axis per input and output (axis i = input i and output i); the plant "
            f"has {plant.n_inputs} input(s) and {plant.n_outputs} output(s), so it cannot run on a drive",
        )
    return plant.n_inputs


def axis_node_ids(drive: DriveConfig, n_axes: int, *, max_node_id: int = NODE_ID_MAX) -> tuple[int, ...]:
    """The node id of each of ``n_axes`` axes: ``drive.node_ids``, or ``node_id + i``.

    ConfigError naming ``drive.node_ids`` (or ``drive.node_id``) when there is not one distinct id
    per axis, each in 0..``max_node_id``.
    """
    if drive.node_ids is None:
        ids = tuple(drive.node_id + i for i in range(n_axes))
        if ids[-1] > max_node_id:
            raise ConfigError(
                "drive.node_id",
                f"{n_axes} axes from node {drive.node_id} need nodes {ids[0]}..{ids[-1]}, beyond "
                f"the protocol's 0..{max_node_id}; give drive.node_ids",
            )
        return ids
    ids = tuple(drive.node_ids)
    if len(ids) != n_axes:
        raise ConfigError(
            "drive.node_ids", f"expected {n_axes} node ids (one per axis: the plant's inputs), got {len(ids)}"
        )
    if len(set(ids)) != len(ids):
        raise ConfigError("drive.node_ids", f"must be distinct, got {list(ids)}")
    for i, node in enumerate(ids):
        if not 0 <= node <= max_node_id:
            raise ConfigError("drive.node_ids", f"entry [{i}] must be in 0..{max_node_id}, got {node}")
    return ids
