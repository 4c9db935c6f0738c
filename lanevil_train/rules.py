"""Rules for settings values: what a good value is (in words, for the message) and a test. The one vocabulary the
components use to check their own parameters (a head's SETTINGS, checked by its constructor) and the config check
uses to report a bad config value by its key before any work. Plain Python: imports nothing of lanevil_train.
"""

from __future__ import annotations

import difflib
import math
import numbers
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable


@dataclass(frozen=True)
class Rule:
    """What a good value is (for the message) and a test: None for a good value, else why not ("" if obvious)."""

    expected: str
    test: Callable[[Any], str | None]


def show(value: Any) -> str:
    """A value as it is written on the command line: null, true, 'text', [1, 2]."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, list):
        return "[" + ", ".join(show(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {show(v)}" for k, v in value.items()) + "}"
    return str(value)


def is_int(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def is_list(value: Any) -> bool:
    """A list (or any sequence but a string: a tuple, OmegaConf's ListConfig in a constructor Hydra called)."""
    return isinstance(value, Sequence) and not isinstance(value, (str, bytes))


def ok(good: bool) -> str | None:
    return None if good else ""


def integer(low: int | None = None, high: int | None = None) -> Rule:
    if high is None:
        expected = "an integer" if low is None else f"an integer >= {low}"
    else:
        expected = f"an integer <= {high}" if low is None else f"an integer from {low} to {high}"
    return Rule(expected, lambda v: ok(is_int(v) and (low is None or v >= low) and (high is None or v <= high)))


def number(low: float | None = None, high: float | None = None, low_open: bool = False,
           high_open: bool = False) -> Rule:
    """A finite real number within the bounds (closed unless *_open), e.g. number(0, 1, high_open=True) for [0, 1)."""
    if high is None:
        expected = f"a number {'>' if low_open else '>='} {low}"
    else:
        expected = f"a number in {'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"

    def test(v):
        if not is_number(v) or not math.isfinite(v):
            return ""
        above = v > low if low_open else v >= low
        below = high is None or (v < high if high_open else v <= high)
        return ok(above and below)
    return Rule(expected, test)


def probability() -> Rule:
    return Rule("a probability in [0, 1]", number(0, 1).test)


def exactly(value: Any) -> Rule:
    return Rule(show(value), lambda v: ok(is_int(v) and v == value))


def boolean() -> Rule:
    return Rule("true or false", lambda v: ok(isinstance(v, bool)))


def text() -> Rule:
    return Rule("a non-empty string", lambda v: ok(isinstance(v, str) and v != ""))


def one_of(*choices: str) -> Rule:
    return Rule(f"one of {', '.join(choices)}", lambda v: ok(isinstance(v, str) and v in choices))


def null_or(rule: Rule) -> Rule:
    return Rule(f"null or {rule.expected}", lambda v: None if v is None else rule.test(v))


def any_of(*rules: Rule) -> Rule:
    return Rule(" or ".join(r.expected for r in rules),
                lambda v: None if any(r.test(v) is None for r in rules) else "")


def int_pair(low: int, names: str = "height, width") -> Rule:
    """[a, b], two integers >= low (an image size)."""
    return Rule(f"[{names}], two integers >= {low}",
                lambda v: ok(is_list(v) and len(v) == 2 and all(is_int(x) and x >= low for x in v)))


def int_list(low: int | None = None, high: int | None = None) -> Rule:
    """A non-empty list of integers in [low, high] (either bound may be left open)."""
    item = integer(low, high)
    return Rule(f"a non-empty list of {item.expected.replace('an integer', 'integers')}",
                lambda v: ok(is_list(v) and len(v) > 0 and all(item.test(x) is None for x in v)))


def number_list(low: float | None = None, low_open: bool = False) -> Rule:
    """A non-empty list of finite numbers (each >= low, or > low when low_open, when low is given)."""
    if low is None:
        item, items = Rule("a number", lambda v: ok(is_number(v) and math.isfinite(v))), "numbers"
    else:
        item = number(low, low_open=low_open)
        items = item.expected.replace("a number", "numbers")
    return Rule(f"a non-empty list of {items}",
                lambda v: ok(is_list(v) and len(v) > 0 and all(item.test(x) is None for x in v)))


def one_or_pair(item: Rule) -> Rule:
    """`item`, or a [min, max] pair of such values with min <= max (a range to draw from)."""
    def test(v):
        if not is_list(v):
            return item.test(v)
        return ok(len(v) == 2 and all(item.test(x) is None for x in v) and v[0] <= v[1])
    return Rule(f"{item.expected}, or a [min, max] pair of them with min <= max", test)


def number_range(low: float) -> Rule:
    """[a, b] with low <= a <= b (a range of numbers)."""
    return Rule(f"[low, high], two numbers with {low} <= low <= high",
                lambda v: ok(is_list(v) and len(v) == 2 and all(is_number(x) for x in v) and low <= v[0] <= v[1]))


def string_list() -> Rule:
    return Rule("a list of strings", lambda v: ok(is_list(v) and all(isinstance(x, str) for x in v)))


def _path_test(kind: str) -> Callable[[Any], str | None]:
    def test(v):
        if not isinstance(v, str) or not v:
            return ""
        path = Path(v)
        if not path.exists():
            return f"no such {kind}"
        if kind == "file" and not path.is_file():
            return "a directory, not a file"
        if kind == "directory" and not path.is_dir():
            return "a file, not a directory"
        return None
    return test


def existing_file(what: str = "file") -> Rule:
    return Rule(f"the path of an existing {what}", _path_test("file"))


def existing_dir(what: str = "directory") -> Rule:
    return Rule(f"the path of an existing {what}", _path_test("directory"))


def problem(key: str, expected: str, value: Any, why: str = "") -> str:
    """The message for a bad value: "key: expected EXPECTED, got VALUE (why)"."""
    return f"{key}: expected {expected}, got {show(value)}" + (f" ({why})" if why else "")


def settings_problems(rules: Mapping[str, Rule], values: Mapping[str, Any], prefix: str) -> list[str]:
    """Every value of `values` its rule in `rules` refuses, one message each, named `prefix.name` (`name` when the
    prefix is empty)."""
    found = []
    for name, rule in rules.items():
        if name in values:
            why = rule.test(values[name])
            if why is not None:
                found.append(problem(f"{prefix}.{name}" if prefix else name, rule.expected, values[name], why))
    return found


def check_settings(rules: Mapping[str, Rule], values: Mapping[str, Any], prefix: str) -> None:
    """Raise ValueError listing every value of `values` its rule refuses (settings_problems); return if all are good."""
    found = settings_problems(rules, values, prefix)
    if found:
        raise ValueError("; ".join(found))


def nearest(name: str, names: Collection[str]) -> str | None:
    """The name of `names` closest to `name` (a likely typo's intent), or None when none is close."""
    found = difflib.get_close_matches(str(name), list(names), n=1, cutoff=0.6)
    return found[0] if found else None


def unknown_settings(names: Collection[str], values: Mapping[str, Any], prefix: str) -> list[str]:
    """One message per key of `values` that is not one of `names`: its dotted path `prefix.key`, the nearest
    setting and all of them, e.g. "task.kalman.memry_s: not a setting of task.kalman; did you mean
    task.kalman.memory_s? its settings: ..."."""
    found = []
    for key in values:
        if key not in names:
            near = nearest(key, names)
            hint = f"did you mean {prefix}.{near}? " if near else ""
            found.append(f"{prefix}.{key}: not a setting of {prefix}; {hint}its settings: {', '.join(names)}")
    return found


def check_group(rules: Mapping[str, Rule], values: Mapping[str, Any], prefix: str) -> None:
    """Raise ValueError listing every key of `values` that is not one of `rules` (unknown_settings) and every value
    its rule refuses (settings_problems): a settings group one class owns whole, e.g. task.kalman."""
    found = unknown_settings(rules, values, prefix) + settings_problems(rules, values, prefix)
    if found:
        raise ValueError("; ".join(found))
