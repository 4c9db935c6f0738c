"""Closed-loop differences between groups of models trained alike: a defense against `none` over training seeds.

Models driven by one task=closed_loop are grouped by their labels, "<group>@<seed>" (as task=compare names a run:
`aam++@3` is AAM++ trained with seed 3). Each group is compared with the reference group (`none` when there is one,
else the first group to drive): per category and over all illusions, the mean difference group - reference of the
ASR (points), the largest deviation (m), the minimum TLC (s) and the false-lane-lock share (points), over the pairs
of perturbed runs with the same (seed, case, illusion, severity, repeat) that both have the score; its 95 %
interval from a paired bootstrap that draws the (seed, case, illusion, repeat) units with replacement. "excludes 0"
says whether the ASR difference's interval lies on one side of zero. The per-seed ASR (mean ± std over the seeds)
shows how much one training run alone could have said.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np

from lanevil_train.report.closed_loop import ALL, MISSING, paired_difference
from lanevil_train.report.intervals import REPLICATES
from lanevil_train.report.records import ordered
from lanevil_train.taxonomy import CATEGORIES

REFERENCE = "none"
LABEL = re.compile(r"^(?P<group>.+)@(?P<seed>\d+)$")

# the differences reported: (column, the record's score or a function of it, scale, digits)
DIFFERENCES = (("ASR Δ (pts)", lambda r: float(bool(r.get("success"))), 100.0, 1),
               ("max dev Δ (m)", "max_deviation_m", 1.0, 3),
               ("min TLC Δ (s)", "tlc_min_s", 1.0, 2),
               ("lane lock Δ (pts)", "lock_share", 100.0, 2))


def group_of(label: str) -> tuple[str, int] | None:
    """("aam++", 3) for the label "aam++@3"; None for a label without "@<seed>"."""
    match = LABEL.match(str(label))
    return (match["group"], int(match["seed"])) if match else None


def groups_of(records: Sequence[dict]) -> dict[str, dict[int, str]] | None:
    """{group: {seed: model label}} when every model's label is "<group>@<seed>" and there are at least two groups
    sharing a seed; otherwise None (no group table)."""
    groups: dict[str, dict[int, str]] = {}
    for model in dict.fromkeys(r["model"] for r in records):
        parsed = group_of(model)
        if parsed is None:
            return None
        groups.setdefault(parsed[0], {})[parsed[1]] = model
    if len(groups) < 2:
        return None
    reference = reference_group(groups)
    if not any(set(seeds) & set(groups[reference]) for name, seeds in groups.items() if name != reference):
        return None
    return groups


def reference_group(groups: dict[str, dict[int, str]]) -> str:
    return REFERENCE if REFERENCE in groups else next(iter(groups))


def _pair(record: dict) -> tuple:
    return group_of(record["model"])[1], record["case_id"], record["illusion"], record["severity"], record["repeat"]


def _unit(record: dict) -> tuple:
    return group_of(record["model"])[1], record["case_id"], record["illusion"], record["repeat"]


def _seed_asr(records: Sequence[dict], seeds: Sequence[int]) -> str:
    """The ASR (%) of each seed's runs, as mean ± std over the seeds (ddof 1)."""
    by_seed = [[r for r in records if group_of(r["model"])[1] == seed] for seed in seeds]
    values = [100.0 * np.mean([bool(r.get("success")) for r in runs]) for runs in by_seed if runs]
    if not values:
        return MISSING
    spread = float(np.std(values, ddof=1)) if len(values) > 1 else 0.0
    return f"{np.mean(values):.1f} ± {spread:.1f}"


def group_difference_rows(records: Sequence[dict], replicates: int = REPLICATES, seed: int = 0) -> list[dict]:
    """One row per compared group and category (then `all`): see the module docstring. [] without groups."""
    groups = groups_of(records)
    if groups is None:
        return []
    reference = reference_group(groups)
    perturbed = [r for r in records if r["perturbed"]]
    categories = ordered({r["category"] for r in perturbed}, tuple(CATEGORIES))
    rows = []
    for name, models in groups.items():
        if name == reference:
            continue
        seeds = sorted(set(models) & set(groups[reference]))
        mine = {models[s] for s in seeds}
        theirs = {groups[reference][s] for s in seeds}
        for category in [*categories, ALL]:
            def keep(r, labels):
                return r["model"] in labels and (category == ALL or r["category"] == category)
            ours = [r for r in perturbed if keep(r, mine)]
            reference_runs = [r for r in perturbed if keep(r, theirs)]
            row = {"group": name, "vs": reference, "category": category, "seeds": len(seeds), "runs": len(ours),
                   f"{reference} ASR (%)": _seed_asr(reference_runs, seeds), f"{name} ASR (%)": _seed_asr(ours, seeds)}
            for column, score, scale, digits in DIFFERENCES:
                difference = paired_difference(ours, reference_runs, score, scale, replicates, seed, _pair,
                                               _unit)
                row[column] = MISSING if difference is None else (
                    f"{difference[0]:+.{digits}f} [{difference[1]:+.{digits}f}, {difference[2]:+.{digits}f}]")
                if column.startswith("ASR"):
                    row["excludes 0"] = MISSING if difference is None else (
                        "yes" if difference[1] > 0 or difference[2] < 0 else "no")
            rows.append(row)
    return rows
