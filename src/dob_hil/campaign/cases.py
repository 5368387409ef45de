"""Cases: the seeded draws crossed with the grids, and each case's (design, truth) configs.

A case is reproducible from the campaign seed and its draw index alone: the draw's seed is
``SeedSequence([campaign seed, draw]).generate_state(1)`` and its values are drawn, in the
order of the ``[[vary]]`` tables, from ``numpy.random.default_rng(draw seed)``. The same seed is
the simulated drive's ``sim.seed`` (its noise and loss). Both grid cases of a draw share it, so
DOB on and off see the same plant and disturbance (a paired comparison).
"""

from __future__ import annotations

import copy
import itertools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import tomllib

from dob_hil.errors import ConfigError

if TYPE_CHECKING:
    from dob_hil.campaign.spec import CampaignSpec, Vary
    from dob_hil.config import Config


@dataclass(frozen=True)
class Case:
    index: int
    case_id: str
    draw: int
    seed: int
    params: tuple[tuple[str, Any], ...]  # (key, value) in the order of the [[vary]] tables

    @property
    def dob_enabled(self) -> bool | None:
        return dict(self.params).get("run.dob_enabled")


def case_id(index: int) -> str:
    return f"c{index:06d}"


def draw_seed(campaign_seed: int, draw: int) -> int:
    return int(np.random.SeedSequence([campaign_seed, draw]).generate_state(1, dtype=np.uint64)[0] >> 1)


def _base_value(spec: CampaignSpec, v: Vary) -> Any:
    node: Any = tomllib.loads(spec.base_text)
    for part in v.path:
        try:
            node = node[part]
        except (KeyError, IndexError, TypeError):
            raise ConfigError(f"vary {v.key}", "no such value in the base config") from None
    return node


def _draw(rng: np.random.Generator, v: Vary, base: Any) -> Any:
    a, b = v.values[0], v.values[-1]
    if v.dist == "uniform":
        return float(rng.uniform(a, b))
    if v.dist == "log_uniform":
        return float(math.exp(rng.uniform(math.log(a), math.log(b))))
    if v.dist == "relative":
        return float(base) * (1.0 + float(rng.uniform(a, b)))
    if v.dist == "normal":
        return float(rng.normal(a, b))
    return v.values[int(rng.integers(len(v.values)))]  # choice


def generate_cases(spec: CampaignSpec) -> list[Case]:
    random = [v for v in spec.vary if v.dist != "grid"]
    bases = {v.key: _base_value(spec, v) for v in random if v.dist == "relative"}
    grid_combos = list(itertools.product(*(v.values for v in spec.grids)))
    cases = []
    for draw in range(spec.samples):
        seed = draw_seed(spec.seed, draw)
        rng = np.random.default_rng(seed)
        drawn = {v.key: _draw(rng, v, bases.get(v.key)) for v in random}
        for g, combo in enumerate(grid_combos):
            values = dict(drawn)
            values.update({v.key: x for v, x in zip(spec.grids, combo, strict=True)})
            index = draw * len(grid_combos) + g
            params = tuple((v.key, values[v.key]) for v in spec.vary)
            cases.append(Case(index, case_id(index), draw, seed, params))
    return cases


def _set(data: dict[str, Any], v: Vary, value: Any) -> None:
    node: Any = data
    for part in v.path[:-1]:
        try:
            node = node[part]
        except (KeyError, IndexError, TypeError):
            raise ConfigError(f"vary {v.key}", "no such value in the base config") from None
    last = v.path[-1]
    try:
        if isinstance(last, int):
            node[last]
        node[last] = value
    except (IndexError, TypeError):
        raise ConfigError(f"vary {v.key}", "no such value in the base config") from None


def case_configs(spec: CampaignSpec, case: Case) -> tuple[Config, Config, bool]:
    """(design config, truth config, DOB on): the design sees the nominal plant, the simulated
    drive the perturbed one; every other varied key applies to both."""
    from dob_hil.config import parse_config

    values = dict(case.params)
    design_data = tomllib.loads(spec.base_text)
    design_data.setdefault("sim", {})["seed"] = case.seed
    for v in spec.vary:
        if not v.truth_only and v.key != "run.dob_enabled":
            _set(design_data, v, values[v.key])
    truth_data = copy.deepcopy(design_data)
    for v in spec.vary:
        if v.truth_only:
            _set(truth_data, v, values[v.key])
    note = "".join(f"# campaign {spec.name} {case.case_id}: {k} = {x!r}\n" for k, x in case.params)
    source = Path(spec.base_source)
    design = parse_config(design_data, source=source, text=note + spec.base_text)
    truth = parse_config(truth_data, source=source, text=note + spec.base_text)
    dob = values.get("run.dob_enabled", design.run.dob_enabled)
    if not isinstance(dob, bool):
        raise ConfigError("vary run.dob_enabled", f"expected true or false, got {dob!r}")
    return design, truth, dob
