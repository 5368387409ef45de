"""The campaign file (TOML): what to run, what varies, how to judge and keep the results.

::

    [campaign]
    name = "paper-robustness"
    base = "paper-step"        # a scenario name, or a config file relative to this file
    seed = 2026
    samples = 500              # random draws; each runs once per combination of the grids
    duration_s = 1.0           # per case (default: the base config's run.duration_s)
    from_s = 0.1               # start of the metrics window (as dob-hil analyze --from)
    metric = "tracking_error_rms"   # ranks the worst cases
    tracking_bound = 0.05      # a case is "within bound" if tracking_error_max <= this
    stable_bound = 10.0        # ... "stable" if it completed and tracking_error_max <= this
    keep_worst = 5             # logs kept for the N worst cases (re-run at the end)
    keep_failures = true       # logs kept for the cases that did not complete
    batch_size = 0             # cases per task on the pool / Dask (0: automatic, <= 20)

    [[vary]]
    key = "plant.A[1][1]"      # plant.* changes the simulated drive's plant (the truth) only
    relative = [-0.3, 0.3]     # nominal * (1 + U(-0.3, 0.3))
    [[vary]]
    key = "sim.disturbance[0].amplitude_A"   # any other key changes design and truth alike
    uniform = [0.0, 0.4]
    [[vary]]
    key = "run.dob_enabled"
    grid = [true, false]

Distributions (exactly one per ``[[vary]]``): ``uniform = [lo, hi]``, ``log_uniform = [lo, hi]``,
``relative = [lo, hi]`` (a factor ``1 + U(lo, hi)`` on the base value), ``normal = [mean, std]``,
``choice = [...]`` (drawn at random) or ``grid = [...]`` (every value, crossed with the draws).
"""

from __future__ import annotations

import hashlib
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tomllib

from dob_hil.errors import ConfigError

DISTRIBUTIONS = ("uniform", "log_uniform", "relative", "normal", "choice", "grid")
_KEY_PART = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)((?:\[\d+\])*)$")
_CAMPAIGN_KEYS = {
    "name", "base", "seed", "samples", "duration_s", "from_s", "metric", "tracking_bound",
    "stable_bound", "keep_worst", "keep_failures", "batch_size",
}  # fmt: skip
METRICS = ("tracking_error_rms", "tracking_error_max", "disturbance_estimate_error_rms")


@dataclass(frozen=True)
class Vary:
    key: str
    path: tuple[str | int, ...]  # dict keys and list indices into the config's TOML
    dist: str
    values: tuple[Any, ...]

    @property
    def truth_only(self) -> bool:
        """The plant is the truth: the design keeps the nominal plant the controller believes."""
        return self.path[0] == "plant"


@dataclass(frozen=True)
class CampaignSpec:
    name: str
    source: str  # the campaign file
    base_text: str  # the base config's TOML
    base_source: str
    seed: int
    samples: int
    duration_s: float | None
    from_s: float
    metric: str
    tracking_bound: float
    stable_bound: float
    keep_worst: int
    keep_failures: bool
    batch_size: int
    vary: tuple[Vary, ...]
    fingerprint: str  # of the campaign and base texts: a journal belongs to one campaign

    @property
    def grids(self) -> tuple[Vary, ...]:
        return tuple(v for v in self.vary if v.dist == "grid")

    @property
    def n_grid(self) -> int:
        return math.prod(len(v.values) for v in self.grids)

    @property
    def n_cases(self) -> int:
        return self.samples * self.n_grid


def parse_key(key: object, where: str) -> tuple[str | int, ...]:
    if not isinstance(key, str) or not key:
        raise ConfigError(where, f"key: expected a dotted config key such as 'plant.B[1]', got {key!r}")
    path: list[str | int] = []
    for part in key.split("."):
        m = _KEY_PART.match(part)
        if not m:
            raise ConfigError(where, f"key {key!r}: cannot read {part!r} (name or name[index])")
        path.append(m.group(1))
        path.extend(int(i) for i in re.findall(r"\[(\d+)\]", m.group(2)))
    return tuple(path)


def _number(value: object, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ConfigError(where, f"expected a finite number, got {value!r}")
    return float(value)


def _parse_vary(item: object, i: int) -> Vary:
    where = f"vary[{i}]"
    if not isinstance(item, dict):
        raise ConfigError(where, "expected a table ([[vary]])")
    unknown = set(item) - {"key", *DISTRIBUTIONS}
    if unknown:
        raise ConfigError(
            where, f"unknown key {sorted(unknown)[0]!r} (expected key and one of {', '.join(DISTRIBUTIONS)})"
        )
    dists = [d for d in DISTRIBUTIONS if d in item]
    if len(dists) != 1:
        raise ConfigError(
            where, f"give exactly one distribution of {', '.join(DISTRIBUTIONS)}, got {len(dists)}"
        )
    dist = dists[0]
    raw = item[dist]
    if not isinstance(raw, list) or not raw:
        raise ConfigError(f"{where}.{dist}", f"expected a non-empty list, got {raw!r}")
    if dist in ("choice", "grid"):
        values = tuple(raw)
    else:
        if len(raw) != 2:
            raise ConfigError(f"{where}.{dist}", f"expected two numbers, got {len(raw)}")
        a, b = (_number(v, f"{where}.{dist}") for v in raw)
        if dist == "normal" and b < 0:
            raise ConfigError(f"{where}.normal", f"std must be >= 0, got {b}")
        if dist != "normal" and not a <= b:
            raise ConfigError(f"{where}.{dist}", f"expected lo <= hi, got [{a}, {b}]")
        if dist == "log_uniform" and not a > 0:
            raise ConfigError(f"{where}.log_uniform", f"bounds must be > 0, got [{a}, {b}]")
        values = (a, b)
    return Vary(str(item.get("key")), parse_key(item.get("key"), where), dist, values)


def _get(table: dict[str, Any], key: str, kind: type, default: Any, low: float | None = None) -> Any:
    value = table.get(key, default)
    ok = isinstance(value, kind) and not (kind is not bool and isinstance(value, bool))
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value, ok = float(value), True
    if not ok:
        raise ConfigError(f"campaign.{key}", f"expected {kind.__name__}, got {value!r}")
    if low is not None and value is not None and not value >= low:
        raise ConfigError(f"campaign.{key}", f"must be >= {low}, got {value}")
    return value


def load_campaign(path: str | Path) -> CampaignSpec:
    """Read and check a campaign file; the base config is read (and checked) too."""
    from dob_hil.config import load_config
    from dob_hil.scenarios import resolve_config_path, scenario_path

    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
        data = tomllib.loads(text)
    except FileNotFoundError:
        raise ConfigError(str(p), "no such campaign file") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(str(p), f"cannot read: {exc}") from None
    unknown = set(data) - {"campaign", "vary"}
    if unknown:
        raise ConfigError(str(p), f"unknown table {sorted(unknown)[0]!r} (expected [campaign] and [[vary]])")
    c = data.get("campaign")
    if not isinstance(c, dict):
        raise ConfigError(str(p), "missing the [campaign] table")
    bad = set(c) - _CAMPAIGN_KEYS
    if bad:
        raise ConfigError(f"campaign.{sorted(bad)[0]}", "unknown key")
    base = c.get("base")
    if not isinstance(base, str) or not base:
        raise ConfigError("campaign.base", "missing: a scenario name or a config file")
    candidate = p.parent / base
    base_path = candidate if candidate.is_file() else resolve_config_path(base)
    if not Path(base_path).is_file():
        base_path = scenario_path(base)
    base_config = load_config(base_path)  # checked here, once, with its own error messages
    vary_raw = data.get("vary", [])
    if not isinstance(vary_raw, list):
        raise ConfigError("vary", "expected [[vary]] tables")
    vary = tuple(_parse_vary(item, i) for i, item in enumerate(vary_raw))
    keys = [v.key for v in vary]
    if len(set(keys)) != len(keys):
        raise ConfigError("vary", "a key is varied twice")
    metric = _get(c, "metric", str, "tracking_error_rms")
    if metric not in METRICS:
        raise ConfigError("campaign.metric", f"expected one of {', '.join(METRICS)}, got {metric!r}")
    duration = _get(c, "duration_s", float, base_config.run.duration_s, low=1e-6)
    spec = CampaignSpec(
        name=_get(c, "name", str, p.stem),
        source=str(p),
        base_text=base_config.text,
        base_source=str(base_path),
        seed=_get(c, "seed", int, 0, low=0),
        samples=_get(c, "samples", int, 1, low=1),
        duration_s=duration,
        from_s=_get(c, "from_s", float, 0.1, low=0.0),
        metric=metric,
        tracking_bound=_get(c, "tracking_bound", float, 0.05, low=0.0),
        stable_bound=_get(c, "stable_bound", float, 10.0, low=0.0),
        keep_worst=_get(c, "keep_worst", int, 5, low=0),
        keep_failures=_get(c, "keep_failures", bool, True),
        batch_size=_get(c, "batch_size", int, 0, low=0),
        vary=vary,
        fingerprint=hashlib.sha256((text + "\0" + base_config.text).encode()).hexdigest()[:16],
    )
    from dob_hil.campaign.cases import case_configs, generate_cases

    first = generate_cases(spec)[:1]
    for case in first:  # every key must exist in the base config and give a valid config
        case_configs(spec, case)
    return spec
