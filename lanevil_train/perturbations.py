"""Every perturbation a robustness suite applies, by name, behind one call: `p(image, ctx, severity, seed)`.

Three kinds of suite (`SUITE_KINDS`):
- illusions: the 14 environmental illusions (illusions/, paper §3.3);
- corruptions: the 11 non-illusion corruptions (corruptions.py: weather, blur, noise, digital; paper §5.4), which
  ignore the scene geometry `ctx`;
- combined: two illusions of different categories applied one after the other to the same scene (paper §5.6),
  named "<a>+<b>" with the category "<category a>+<category b>". A combined suite scores, for each case, one
  illusion per category alone and each pair of them, so a pair's Gap can be read against the original and against
  each of its single illusions on the same images.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations
from typing import Sequence

import numpy as np

from lanevil_train.illusions.registry import ILLUSIONS, Illusion, check_seed, check_severity
from lanevil_train.taxonomy import CATEGORIES, ILLUSION_CATEGORY, ILLUSION_NAMES, PAIR

SUITE_KINDS = ("illusions", "corruptions", "combined")


@dataclass(frozen=True)
class Combined:
    """Two illusions of different categories, the first drawn, then the second over it, each with the variant's
    seed: exactly the pixels each would draw alone on the same case."""

    first: Illusion
    second: Illusion

    @property
    def name(self) -> str:
        return f"{self.first.name}{PAIR}{self.second.name}"

    @property
    def category(self) -> str:
        return f"{self.first.category}{PAIR}{self.second.category}"

    def __call__(self, image: np.ndarray, ctx, severity: int, seed: int = 0) -> np.ndarray:
        check_severity(severity)
        seed = check_seed(seed)
        return self.second(self.first(image, ctx, severity, seed), ctx, severity, seed)


def _corruptions():
    from lanevil_train import corruptions  # albumentations is imported only by suites that use it

    return corruptions


def get_perturbation(name: str):
    """The illusion, corruption or illusion pair ("<a>+<b>") called `name`; ValueError listing the known names."""
    if not isinstance(name, str):
        raise ValueError(f"a perturbation name must be a string, got {name!r}")
    if name in ILLUSIONS:
        return ILLUSIONS[name]
    if PAIR in name:
        parts = name.split(PAIR)
        if len(parts) != 2 or any(p not in ILLUSIONS for p in parts):
            raise ValueError(f"unknown illusion pair {name!r}: expected '<illusion>+<illusion>' with two of "
                             f"{', '.join(ILLUSION_NAMES)}")
        if ILLUSION_CATEGORY[parts[0]] == ILLUSION_CATEGORY[parts[1]]:
            raise ValueError(f"illusion pair {name!r}: both illusions are {ILLUSION_CATEGORY[parts[0]]}; a combined "
                             f"illusion pairs two categories")
        return Combined(ILLUSIONS[parts[0]], ILLUSIONS[parts[1]])
    corruptions = _corruptions()
    if name in corruptions.CORRUPTIONS:
        return corruptions.CORRUPTIONS[name]
    raise ValueError(f"unknown perturbation {name!r}; expected an illusion ({', '.join(ILLUSION_NAMES)}), a corruption "
                     f"({', '.join(corruptions.CORRUPTION_NAMES)}) or an illusion pair '<a>+<b>'")


def check_kind(kind: str) -> str:
    if kind not in SUITE_KINDS:
        raise ValueError(f"suite kind: expected one of {list(SUITE_KINDS)}, got {kind!r}")
    return kind


def suite_names(kind: str, names: str | Sequence[str] = "all") -> tuple[str, ...]:
    """The names a suite of `kind` draws from ("all", or a list checked against the kind): illusions for the
    illusion and combined suites, corruptions for the corruption suite. A combined suite needs illusions of at least
    two categories."""
    check_kind(kind)
    known = _corruptions().CORRUPTION_NAMES if kind == "corruptions" else ILLUSION_NAMES
    if isinstance(names, str):
        if names != "all":
            raise ValueError(f"illusions: expected 'all' or a list of names, got {names!r}")
        return tuple(known)
    names = tuple(names)
    if not names:
        raise ValueError(f"illusions: expected 'all' or a non-empty list of {kind} names, got an empty list")
    for i, name in enumerate(names):
        if name not in known:
            noun = "corruption" if kind == "corruptions" else "illusion"
            raise ValueError(f"illusions[{i}]: unknown {noun} {name!r}; the {kind} suite's names: {', '.join(known)}")
    if len(set(names)) != len(names):
        raise ValueError(f"illusions: {list(names)} lists a name twice")
    if kind == "combined" and len({ILLUSION_CATEGORY[n] for n in names}) < 2:
        raise ValueError(f"illusions: a combined suite pairs illusions of two categories; {list(names)} are all "
                         f"{ILLUSION_CATEGORY[names[0]]}")
    return names


def combined_choice(seed: int, names: Sequence[str]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(single illusions, illusion pairs) of one combined-suite case: one illusion per category among `names`,
    drawn from the case seed, and every pair of them across categories, in the paper's category order
    (RD+TO, RD+SH, RD+RF, TO+SH, TO+RF, SH+RF)."""
    rng = np.random.default_rng(check_seed(seed))
    singles = []
    for category, members in CATEGORIES.items():
        allowed = [n for n in members if n in names]
        if allowed:
            singles.append(allowed[int(rng.integers(len(allowed)))])
    pairs = tuple(f"{a}{PAIR}{b}" for a, b in combinations(singles, 2))
    return tuple(singles), pairs


def case_perturbations(kind: str, names: Sequence[str], seed: int) -> tuple[str, ...]:
    """The perturbations a case of a `kind` suite gets (each at every severity): `names` itself, or for a combined
    suite the case's single illusions and their pairs (combined_choice)."""
    if check_kind(kind) == "combined":
        singles, pairs = combined_choice(seed, names)
        return singles + pairs
    return tuple(names)
