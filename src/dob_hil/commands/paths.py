"""Output folders and files of the commands: created up front, refused with one line naming the
option when they cannot be (a file in the way, no permission, a read-only file system)."""

from __future__ import annotations

import os
from pathlib import Path

from dob_hil.errors import ConfigError


def _reason(exc: OSError) -> str:
    return exc.strerror or type(exc).__name__


def ensure_dir(path: Path, option: str) -> Path:
    """Create the folder ``path`` (and its parents) if needed; it must end up writable."""
    if path.exists() and not path.is_dir():
        raise ConfigError(option, f"{path} is a file, not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise ConfigError(option, f"cannot create folder {path}: a file is in the way") from None
    except OSError as exc:
        raise ConfigError(option, f"cannot create folder {path}: {_reason(exc)}") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise ConfigError(
            option, f"cannot write into folder {path}: no permission or a read-only file system"
        )
    return path


def ensure_file_parent(path: Path, option: str) -> Path:
    """A file about to be written: its folder is created and writable, and it is no folder."""
    if path.is_dir():
        raise ConfigError(option, f"{path} is a folder, not a file")
    ensure_dir(path.parent if str(path.parent) else Path("."), option)
    return path
