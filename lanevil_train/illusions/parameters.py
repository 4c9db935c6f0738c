"""An illusion's physical parameters as a typed, bounded space, and its points (`Illusion.parameters()`).

Every illusion is drawn from one parameter dict (its category module's LEVELS[name][severity - 1] is the dict of a
severity). The space of an illusion has one `Parameter` per key of those dicts, bounded by the range its five
severity levels span (min..max over LEVELS); a key whose value is the same at every level is *fixed* (low == high):
it is part of every point but a search does not vary it. A *point* is a dict of values, one per parameter (fixed
ones may be left out); `ParameterSpace.check` types it (int or float) and refuses a value outside its range.

A point is drawn like a severity: the renderer lays its items out for the space's upper bounds (the most items of
any level, the widest sweep, ...) and the point's counts and extents choose how much of that layout it shows, so
two points of one seed differ in degree, not layout, and each severity's point renders exactly that severity.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from lanevil_train.taxonomy import SEVERITIES

UNITS = {"_m": "m", "_deg": "deg", "_px": "px at 1280 px wide", "_frac": "fraction", "_prob": "probability",
         "_factor": "brightness gain"}  # by the end of a parameter's name; none: dimensionless (opacity, intensity)


@dataclass(frozen=True)
class Parameter:
    """One physical parameter of an illusion: its name, kind ("int" or "float"), range [low, high] and unit."""

    name: str
    kind: str
    low: float
    high: float
    unit: str = ""

    @property
    def fixed(self) -> bool:
        """The same at every severity level: part of every point, not searched."""
        return self.low == self.high

    def describe(self) -> str:
        """E.g. 'opacity (float in [0.25, 0.65])' or 'sides (fixed at 2)'."""
        unit = f" {self.unit}" if self.unit else ""
        if self.fixed:
            return f"{self.name} (fixed at {self.low:g}{unit})"
        return f"{self.name} ({self.kind} in [{self.low:g}, {self.high:g}]{unit})"

    def check(self, value, illusion: str) -> int | float:
        """`value` typed as this parameter's kind, or a ValueError naming the parameter, the value and the range."""
        where = f"{illusion}: parameter {self.name}"
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise ValueError(f"{where} must be a number, got {value!r} (expected {self.describe()})")
        if not math.isfinite(float(value)):
            raise ValueError(f"{where} must be finite, got {value!r} (expected {self.describe()})")
        if self.kind == "int" and float(value) != int(value):
            raise ValueError(f"{where} must be a whole number, got {value!r} (expected {self.describe()})")
        typed = int(value) if self.kind == "int" else float(value)
        if not self.low <= typed <= self.high:
            bound = f"is fixed at {self.low:g}" if self.fixed else f"has range [{self.low:g}, {self.high:g}]"
            raise ValueError(f"{where} = {value!r} is outside its bounds: {self.name} {bound}")
        return typed

    def midpoint(self) -> int | float:
        """The middle of the range (rounded down for an int)."""
        middle = (self.low + self.high) / 2.0
        return int(math.floor(middle)) if self.kind == "int" else middle


@dataclass(frozen=True)
class ParameterSpace:
    """The parameters of one illusion, in its LEVELS' key order; iterate it, or look a parameter up by name."""

    illusion: str
    parameters: tuple[Parameter, ...]

    def __iter__(self) -> Iterator[Parameter]:
        return iter(self.parameters)

    def __len__(self) -> int:
        return len(self.parameters)

    def __getitem__(self, name: str) -> Parameter:
        for parameter in self.parameters:
            if parameter.name == name:
                return parameter
        raise KeyError(f"{self.illusion} has no parameter {name!r}; it has: {', '.join(self.names)}")

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(parameter.name for parameter in self.parameters)

    @property
    def searched(self) -> tuple[Parameter, ...]:
        """The parameters a search varies (the fixed ones left out)."""
        return tuple(parameter for parameter in self.parameters if not parameter.fixed)

    def check(self, point: Mapping) -> dict:
        """The full point (every parameter, typed; fixed ones filled in) of a dict of values, or a ValueError naming
        the parameter that is unknown, missing or out of its bounds."""
        if not isinstance(point, Mapping):
            raise ValueError(f"{self.illusion}: a point is a dict of parameter values, got {type(point).__name__}")
        unknown = [key for key in point if key not in self.names]
        if unknown:
            raise ValueError(f"{self.illusion} has no parameter {unknown[0]!r}; it has: {', '.join(self.names)}")
        out = {}
        for parameter in self.parameters:
            if parameter.name in point:
                out[parameter.name] = parameter.check(point[parameter.name], self.illusion)
            elif parameter.fixed:
                out[parameter.name] = parameter.check(parameter.low, self.illusion)
            else:
                raise ValueError(f"{self.illusion}: the point has no value for {parameter.describe()}")
        return out

    def midpoint(self) -> dict:
        """The point in the middle of every range."""
        return {parameter.name: parameter.midpoint() for parameter in self.parameters}


def parameter_space(illusion: str, levels: Sequence[Mapping], integers: frozenset[str]) -> ParameterSpace:
    """The space the severity levels of `illusion` span: a key of `integers` is an int parameter, any other a float."""
    keys = list(levels[0])
    for severity, level in enumerate(levels, 1):
        if list(level) != keys:
            raise RuntimeError(f"illusion {illusion}: level {severity} has keys {list(level)}, level 1 has {keys}")
    parameters = []
    for key in keys:
        values = [level[key] for level in levels]
        kind = "int" if key in integers else "float"
        parameters.append(Parameter(key, kind, min(values), max(values), "" if kind == "int" else _unit(key)))
    return ParameterSpace(illusion, tuple(parameters))


def _unit(key: str) -> str:
    return next((unit for suffix, unit in UNITS.items() if key.endswith(suffix)), "")


def check_severity(severity) -> int:
    """Severity as an int in 1..5, or a ValueError saying what was expected."""
    if isinstance(severity, bool) or not isinstance(severity, (int, np.integer)) or severity not in SEVERITIES:
        raise ValueError(f"severity must be an integer from 1 (subtle) to 5 (severe), got {severity!r}")
    return int(severity)


def level_params(levels: Sequence[Mapping], level: Mapping | int) -> Mapping:
    """The parameter dict a renderer draws: `level` itself (a point, or a LEVELS entry), or for a severity 1..5 its
    entry of `levels`."""
    return level if isinstance(level, Mapping) else levels[check_severity(level) - 1]


def introduced(levels: Sequence[Mapping], count_key: str, i: int, key: str, p: Mapping) -> float:
    """`key` of item i: the value of the lowest level that has the item (levels[k][count_key] > i), at most the
    point's own. An item is placed by the rules of the level that introduced it, so it stays put while higher
    levels enlarge it and add more; the point's `key` caps it (the levels' values grow with severity, so a
    severity's own point never caps them)."""
    first = next((lv for lv in levels if lv[count_key] > i), levels[-1])
    return min(p[key], first[key])
