"""The 14 illusions by name, each bound to its renderer and levels (names and categories: lanevil_train.taxonomy).

Each category module (road_damage, traffic, shadow, reflection) exposes RENDERERS (name ->
render(image, ctx, level, rng), `level` a parameter dict), LEVELS (name -> five parameter dicts, severity 1..5) and
INTEGER_KEYS (the parameters that are whole numbers). An illusion renders a severity (`illusion(image, ctx, 3)`)
or any point of its parameter space (`illusion.render_point(image, ctx, point)`, `illusion.parameters()`:
illusions/parameters.py).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from types import MappingProxyType
from typing import Callable

import numpy as np

from lanevil_train.illusions import reflection, road_damage, shadow, traffic
from lanevil_train.illusions.context import IllusionContext
from lanevil_train.illusions.parameters import ParameterSpace, check_severity, parameter_space
from lanevil_train.taxonomy import CATEGORIES, SEVERITIES

_MODULES = {"road_damage": road_damage, "traffic_obstruction": traffic, "shadow": shadow, "reflection": reflection}


@dataclass(frozen=True)
class Illusion:
    """One illusion type: its name, category, renderer, per-severity parameters and which of them are whole numbers."""

    name: str
    category: str
    render: Callable[[np.ndarray, IllusionContext, Mapping, np.random.Generator], np.ndarray] = field(repr=False)
    levels: tuple[dict, ...] = field(repr=False)
    integer_keys: frozenset[str] = field(default=frozenset(), repr=False)

    def __call__(self, image: np.ndarray, ctx: IllusionContext, severity: int, seed: int = 0) -> np.ndarray:
        """Render this illusion at `severity` (1..5) on an image whose geometry `ctx` describes."""
        level = self.levels[check_severity(severity) - 1]
        return self._draw(image, ctx, level, seed)

    def render_point(self, image: np.ndarray, ctx: IllusionContext, point: Mapping, seed: int = 0) -> np.ndarray:
        """Render this illusion at a point of its parameter space (a dict of values, see `parameters()`); a value
        outside its bounds is a ValueError naming the parameter, the value and the range. A severity's point
        (`point(severity)`) renders exactly as that severity."""
        return self._draw(image, ctx, self.parameters().check(point), seed)

    def parameters(self) -> ParameterSpace:
        """The illusion's physical parameters, typed and bounded by the range its five severity levels span."""
        return self._space

    def point(self, severity: int) -> dict:
        """The point of a severity 1..5: a copy of its parameters, to render as it is or to change and render."""
        return dict(self.levels[check_severity(severity) - 1])

    @cached_property
    def _space(self) -> ParameterSpace:
        return parameter_space(self.name, self.levels, self.integer_keys)

    def _draw(self, image: np.ndarray, ctx: IllusionContext, level: Mapping, seed: int) -> np.ndarray:
        # one stream per seed, shared by all severities and points: a case's variants differ in degree, not layout
        return self.render(image, ctx, level, np.random.default_rng(check_seed(seed)))


def _build() -> dict[str, Illusion]:
    table = {}
    for category, names in CATEGORIES.items():
        module = _MODULES[category]
        for name in names:
            levels = tuple(module.LEVELS[name])
            if len(levels) != len(SEVERITIES):
                raise RuntimeError(f"illusion {name}: expected {len(SEVERITIES)} severity levels, got {len(levels)}")
            table[name] = Illusion(name, category, module.RENDERERS[name], levels, module.INTEGER_KEYS)
    return table


ILLUSIONS = MappingProxyType(_build())


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
