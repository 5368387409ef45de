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


def scenario_variant(
    name: str, directory: Path, *, node_id: int, patience_periods: int | None = None
) -> Path:
    """A shipped scenario with its own drive node id (and, given ``patience_periods``, the
    watchdog and host timeout widened to that many periods), written into ``directory``.

    For real-time runs that share a bus with others (udp_multicast delivers every group's frames
    to every socket on its port) and for noisy machines where a VM stall of a few ms must not end
    a run. The shipped text is edited line by line; a line that is not there is an error.
    """
    text = scenario_path(name).read_text()
    edits = [("node_id = 1\n", f"node_id = {node_id}\n")]
    if patience_periods is not None:
        edits += [(f"{key} = 10\n", f"{key} = {patience_periods}\n")
                  for key in ("watchdog_periods", "feedback_timeout_periods")]  # fmt: skip
    for old, new in edits:
        if old not in text:
            raise ConfigError(name, f"the shipped scenario no longer contains {old.strip()!r}")
        text = text.replace(old, new)
    path = directory / f"{name}-node{node_id}.toml"
    path.write_text(text)
    return path
