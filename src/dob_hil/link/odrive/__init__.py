"""The ODrive CANSimple profile's host side: codec, ``[drive.odrive]`` options, DriveLink, DBC."""

from __future__ import annotations

from importlib import resources
from importlib.abc import Traversable

DBC_NAME = "odrive_cansimple.dbc"


def dbc_resource() -> Traversable:
    """The shipped DBC (ids of node 0; node n's id is ``n << 5`` plus the id given)."""
    return resources.files("dob_hil.link.odrive") / DBC_NAME
