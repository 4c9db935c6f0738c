"""Seeds and confidence intervals: is a defense's gain over `none` (or a model's over a baseline) real, or noise?

Input: {name: {seed: records}}, every run (a name trained with one seed) scored on the same suite. For every name,
group (each illusion category, the average of the categories, the clean original) and score:

- the score of each seed's run, their mean and sample std (`seed_rows`);
- the gain over the reference name, mean over seeds, with a 95 % interval from a paired, two-level bootstrap
  (`gain_rows`): each replicate draws the test cases with replacement (one draw shared by every run, so both sides of
  a gain are scored on the same images: paired) and the seeds with replacement (jointly for both sides when they were
  trained with the same seeds, so seed s of the defense stays paired with seed s of the reference); the replicate's
  gain is the defense's mean over its drawn seeds minus the reference's. The interval is the percentile interval of
  the replicates, so it holds both the test set's sampling noise and the training noise across seeds. A gain is
  distinguishable from zero when its interval excludes 0; a gain of exactly zero on every case never is.

A case is (dataset, case_id): every image of a simulated scene (its original and all its perturbed variants), or
every answer about a clip, are resampled together. With few seeds the seed level of the bootstrap under-covers (with
n seeds its variance is (n - 1) / n of the usual estimate): 3 seeds are the least that say anything.
Scores with an `additive` form (report/records.py: means, TuSimple F1 and F1_count, CULane F1, judge scores) are
resampled as matrix products; others (the corpus-level Language score) are re-aggregated per replicate, which is
slower: they get the first SLOW_REPLICATES replicates only (a VLM compare's Language score costs about 12 ms a
replicate and group).
"""

from __future__ import annotations

import math
from collections import defaultdict
from typing import Sequence

import numpy as np

from lanevil_train.report.records import AVERAGE, RecordSet, Score
from lanevil_train.report.specs import spec_for

ORIGINAL = "original"
REPLICATES = 1000
CONFIDENCE = 0.95
SLOW_REPLICATES = 200  # at most this many replicates for a score re-aggregated per replicate (no additive form)


def case_key(record: dict) -> tuple:
    """The case a record belongs to, what the bootstraps draw: (dataset, case_id)."""
    return record["dataset"], record["case_id"]


class _RunStats:
    """One run's records as per-case sufficient statistics of each (group, score): what a replicate re-weights."""

    def __init__(self, rs: RecordSet, cases: dict[tuple, int], groups: list[str], scores: Sequence[Score]):
        index = rs.by_model[rs.models[0]]
        by_group: dict[str, list[dict]] = defaultdict(list)
        for r in index.pert:
            by_group[r["category"]].append(r)
        by_group[ORIGINAL] = list(index.clean.values())
        self.stats: dict[tuple[str, str], object] = {}
        for group in groups:
            records = by_group.get(group, [])
            for score in scores:
                additive = getattr(score.aggregate, "additive", None)
                if not records:
                    self.stats[group, score.name] = None  # a category this run has no records of
                elif additive is not None:
                    table = np.zeros((len(cases), len(additive.parts(records[0]))))
                    for r in records:
                        table[cases[case_key(r)]] += additive.parts(r)
                    self.stats[group, score.name] = (additive.combine, table)
                else:
                    per_case: list[list[dict]] = [[] for _ in cases]
                    for r in records:
                        per_case[cases[case_key(r)]].append(r)
                    self.stats[group, score.name] = (score.aggregate, per_case)

    def values(self, group: str, score: str, weights: np.ndarray) -> np.ndarray:
        """The score of `group` under each row of case weights (R, n_cases) -> (R,)."""
        if self.stats[group, score] is None:
            return np.full(len(weights), np.nan)
        combine, table = self.stats[group, score]
        if isinstance(table, np.ndarray):
            return combine(weights @ table)
        out = np.empty(len(weights))
        for row, w in enumerate(weights):
            records = [r for i, count in enumerate(w) for _ in range(int(count)) for r in table[i]]
            out[row] = combine(records) if records else math.nan
        return out


class SeedRuns:
    """Runs of several names x seeds on one suite, checked comparable, with their per-case statistics."""

    def __init__(self, runs: dict[str, dict[int, list[dict]]]):
        if not runs or any(not seeds for seeds in runs.values()):
            raise ValueError("seed runs: every name needs the records of at least one seed")
        first = next(iter(next(iter(runs.values())).values()))
        self.spec = spec_for(first)
        self.sets: dict[str, dict[int, RecordSet]] = {}
        for name, seeds in runs.items():
            self.sets[name] = {}
            for seed, records in seeds.items():
                try:
                    rs = RecordSet(list(records), self.spec)
                except (TypeError, ValueError) as error:
                    raise ValueError(f"{name} seed {seed}: {error}") from error
                if len(rs.models) != 1:
                    raise ValueError(f"{name} seed {seed}: expected the records of one model, got {rs.models}")
                self.sets[name][seed] = rs
        all_sets = [rs for seeds in self.sets.values() for rs in seeds.values()]
        case_sets = {frozenset(case_key(r) for r in rs.records) for rs in all_sets}
        if len(case_sets) != 1:
            raise ValueError("seed runs: the runs were scored on different test cases; intervals pair the same cases "
                             "across runs, so score every run on the same suite (cases, illusions, severities)")
        self.cases = {case: i for i, case in enumerate(sorted(next(iter(case_sets)), key=str))}
        self.categories = list(dict.fromkeys(c for rs in all_sets for c in rs.categories))
        self.scores = [s for s in all_sets[0].scores if all(s.name in {x.name for x in rs.scores} for rs in all_sets)]
        groups = [*self.categories, ORIGINAL]
        self.stats = {name: {seed: _RunStats(rs, self.cases, groups, self.scores) for seed, rs in seeds.items()}
                      for name, seeds in self.sets.items()}

    @property
    def groups(self) -> list[str]:
        return [*self.categories, AVERAGE, ORIGINAL]

    def values(self, name: str, seed: int, group: str, score: str, weights: np.ndarray) -> np.ndarray:
        """A run's score under case weights; AVERAGE is the mean of the category values (NaN ones left out)."""
        stats = self.stats[name][seed]
        if group != AVERAGE:
            return stats.values(group, score, weights)
        per_cat = np.stack([stats.values(c, score, weights) for c in self.categories])
        with np.errstate(invalid="ignore"):
            return np.nanmean(per_cat, axis=0) if np.isfinite(per_cat).any() else per_cat[0]


def seed_rows(runs: SeedRuns) -> list[dict]:
    """One row per (name, group): each score's mean and sample std over the seeds, the seeds' values, their count."""
    ones = np.ones((1, len(runs.cases)))
    rows = []
    for name, seeds in runs.stats.items():
        for group in runs.groups:
            row = {"name": name, "category": group, "seeds": len(seeds)}
            for score in runs.scores:
                values = [float(runs.values(name, seed, group, score.name, ones)[0]) for seed in seeds]
                mean = float(np.mean(values))
                std = float(np.std(values, ddof=1)) if len(values) > 1 else math.nan
                row.update({score.name: mean, f"{score.name}/std": std,
                            f"{score.name}/runs": [round(v, 4) for v in values]})
            rows.append(row)
    return rows


def gain_rows(runs: SeedRuns, reference: str, replicates: int = REPLICATES, confidence: float = CONFIDENCE,
              seed: int = 0) -> list[dict]:
    """One row per (name other than `reference`, group): for each score the mean gain over seeds, its interval
    (low, high) and whether the interval excludes zero (see the module docstring)."""
    if reference not in runs.stats:
        raise ValueError(f"the reference {reference!r} has no runs; names: {list(runs.stats)}")
    if isinstance(replicates, bool) or not isinstance(replicates, int) or replicates < 100:
        raise ValueError(f"replicates: expected an integer >= 100 bootstrap replicates, got {replicates!r}")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence: expected a level in (0, 1), e.g. 0.95, got {confidence!r}")
    rng = np.random.default_rng(seed)
    n_cases = len(runs.cases)
    weights = rng.multinomial(n_cases, np.full(n_cases, 1.0 / n_cases), size=replicates).astype(float)
    ones = np.ones((1, n_cases))
    ref_seeds = sorted(runs.stats[reference])
    alpha = (1 - confidence) / 2
    rows = []
    for name in runs.stats:
        if name == reference:
            continue
        seeds = sorted(runs.stats[name])
        paired = seeds == ref_seeds
        draw = rng.integers(len(seeds), size=(replicates, len(seeds)))
        ref_draw = draw if paired else rng.integers(len(ref_seeds), size=(replicates, len(ref_seeds)))
        for group in runs.groups:
            row = {"name": name, "category": group, "seeds": len(seeds), "reference_seeds": len(ref_seeds),
                   "paired_seeds": paired}
            for score in runs.scores:
                r = replicates if getattr(score.aggregate, "additive", None) else min(replicates, SLOW_REPLICATES)
                mine = np.stack([runs.values(name, s, group, score.name, weights[:r]) for s in seeds])  # (S, r)
                ref = np.stack([runs.values(reference, s, group, score.name, weights[:r]) for s in ref_seeds])
                boot = (np.take_along_axis(mine, draw[:r].T, axis=0).mean(axis=0)
                        - np.take_along_axis(ref, ref_draw[:r].T, axis=0).mean(axis=0))
                point = (np.mean([runs.values(name, s, group, score.name, ones)[0] for s in seeds])
                         - np.mean([runs.values(reference, s, group, score.name, ones)[0] for s in ref_seeds]))
                finite = boot[np.isfinite(boot)]
                low, high = (np.quantile(finite, [alpha, 1 - alpha]) if len(finite) else (math.nan, math.nan))
                row.update({f"{score.name}/gain": float(point), f"{score.name}/low": float(low),
                            f"{score.name}/high": float(high),
                            f"{score.name}/distinguishable": bool(low > 0 or high < 0)})
            rows.append(row)
    return rows


def gain_text(row: dict, score: str) -> str:
    """"+1.23 [+0.40, +2.05] *" -- the gain, its interval, and * when the interval excludes zero."""
    gain, low, high = row[f"{score}/gain"], row[f"{score}/low"], row[f"{score}/high"]
    if math.isnan(gain):
        return "n/a"
    mark = " *" if row[f"{score}/distinguishable"] else ""
    return f"{gain:+.2f} [{low:+.2f}, {high:+.2f}]{mark}"


def mean_std_text(row: dict, score: str) -> str:
    """"85.12 ± 0.43" (just the mean for one seed)."""
    mean, std = row[score], row[f"{score}/std"]
    return f"{mean:.2f}" if math.isnan(std) else f"{mean:.2f} ± {std:.2f}"
