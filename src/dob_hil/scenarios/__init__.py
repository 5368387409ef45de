"""Shipped scenarios: TOML configs that reproduce the paper's simulations."""

from __future__ import annotations

from pathlib import Path

from dob_hil.errors import ConfigError

_HERE = Path(__file__).resolve().parent


def scenario_names() -> list[str]:
    return sorted(p.stem for p in _HERE.glob("*.toml"))


def scenario_path(name: str) -> Path:
    path = _HERE / f"{name}.toml"
    if not path.is_file():
        raise ConfigError("--scenario", f"unknown scenario {name!r}; shipped: {', '.join(scenario_names())}")
    return path


def resolve_config_path(arg: str) -> Path:
    """A config argument is a file path, or else the name of a shipped scenario."""
    path = Path(arg)
    if path.is_file():
        return path
    if path.suffix == "" and (_HERE / f"{arg}.toml").is_file():
        return _HERE / f"{arg}.toml"
    raise ConfigError(arg, f"no such config file (and not a shipped scenario: {', '.join(scenario_names())})")
