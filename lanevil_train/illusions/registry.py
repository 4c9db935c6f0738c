"""The 14 illusions by name, each bound to its renderer and levels (names and categories: lanevil_train.taxonomy).

Each category module (road_damage, traffic, shadow, reflection) exposes RENDERERS (name ->
render(image, ctx, severity, rng)) and LEVELS (name -> five parameter dicts, severity 1..5).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Callable

import numpy as np

from lanevil_train.illusions import reflection, road_damage, shadow, traffic
from lanevil_train.illusions.context import IllusionContext
from lanevil_train.taxonomy import CATEGORIES, SEVERITIES

_MODULES = {"road_damage": road_damage, "traffic_obstruction": traffic, "shadow": shadow, "reflection": reflection}


@dataclass(frozen=True)
class Illusion:
    """One illusion type: its name, category, renderer and per-severity parameters."""

    name: str
    category: str
    render: Callable[[np.ndarray, IllusionContext, int, np.random.Generator], np.ndarray] = field(repr=False)
    levels: tuple[dict, ...] = field(repr=False)

    def __call__(self, image: np.ndarray, ctx: IllusionContext, severity: int, seed: int = 0) -> np.ndarray:
        """Render this illusion at `severity` (1..5) on an image whose geometry `ctx` describes."""
        check_severity(severity)
        seed = check_seed(seed)
        # one stream per seed, shared by all severities: a case's variants differ in degree, not layout
        return self.render(image, ctx, severity, np.random.default_rng(seed))


def _build() -> dict[str, Illusion]:
    table = {}
    for category, names in CATEGORIES.items():
        module = _MODULES[category]
        for name in names:
            levels = tuple(module.LEVELS[name])
            if len(levels) != len(SEVERITIES):
                raise RuntimeError(f"illusion {name}: expected {len(SEVERITIES)} severity levels, got {len(levels)}")
            table[name] = Illusion(name, category, module.RENDERERS[name], levels)
    return table


ILLUSIONS = MappingProxyType(_build())


def check_severity(severity) -> int:
    """Severity as an int in 1..5, or a ValueError saying what was expected."""
    if isinstance(severity, bool) or not isinstance(severity, (int, np.integer)) or severity not in SEVERITIES:
        raise ValueError(f"severity must be an integer from 1 (subtle) to 5 (severe), got {severity!r}")
    return int(severity)


def check_seed(seed) -> int:
    """Seed as an int >= 0 (numpy integers too), or a ValueError saying what was expected."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
    return int(seed)


def get_illusion(name: str) -> Illusion:
    """The illusion called `name`, or a ValueError listing the known names."""
    if name not in ILLUSIONS:
        raise ValueError(f"unknown illusion {name!r}; expected one of: {', '.join(ILLUSIONS)}")
    return ILLUSIONS[name]
