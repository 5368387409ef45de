"""The drive profile registry: ``drive.profile`` names one of these.

Every module or package directly inside :mod:`dob_hil.profiles` (other than ``base``) that defines
a module-level ``PROFILE`` (a :class:`~dob_hil.profiles.base.DriveProfile`) is a profile; the
registry finds them on first use. Adding a profile is adding one module here (the descriptor) plus
its codec and link and its simulated counterpart in ``firmware_sim``: nothing else changes.
"""

from __future__ import annotations

import importlib
import pkgutil

from dob_hil.errors import ConfigError
from dob_hil.profiles.base import Clocking, DriveProfile, SimulatedCounterpart

__all__ = ["Clocking", "DriveProfile", "SimulatedCounterpart", "all_profiles", "get_profile", "profile_names"]

_registry: dict[str, DriveProfile] = {}


def _discover() -> dict[str, DriveProfile]:
    if not _registry:
        found: dict[str, DriveProfile] = {}
        for info in pkgutil.iter_modules(__path__):
            if info.name == "base" or info.name.startswith("_"):
                continue
            module = importlib.import_module(f"{__name__}.{info.name}")
            profile = getattr(module, "PROFILE", None)
            if isinstance(profile, DriveProfile):
                if profile.name in found:
                    raise RuntimeError(f"two drive profiles are named {profile.name!r}")
                found[profile.name] = profile
        _registry.update(sorted(found.items()))
    return _registry


def profile_names() -> tuple[str, ...]:
    return tuple(_discover())


def all_profiles() -> tuple[DriveProfile, ...]:
    return tuple(_discover().values())


def get_profile(name: str) -> DriveProfile:
    """The profile called ``name``, or a ConfigError on ``drive.profile`` listing the choices."""
    profiles = _discover()
    try:
        return profiles[name]
    except KeyError:
        raise ConfigError("drive.profile", f"must be one of {', '.join(profiles)}; got {name!r}") from None
