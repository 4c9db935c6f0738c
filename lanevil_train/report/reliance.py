"""Visual reliance: how much of a VLM's accuracy needs the frames.

A VLM's yes/no or choice accuracy is evidence of seeing only beyond what its blind baselines reach on the same
questions: the same model on grey frames (`<model>-blind`) and a text-only reader fitted on the training QA
(`<model>-text`, vlm/backends/text_only.py). For each QA category (and all of them) and each closed type, the
reliance is the model's accuracy minus the better baseline's (the better one by its point estimate), with a 95 %
interval from a paired bootstrap: each replicate draws the test scenes with replacement, one draw for the model and
its baselines alike (every answer about a scene's clips and variants moves together, as in report/intervals.py).
An interval that excludes 0 says the model answers better with the frames than any reading of the words can.
"""

from __future__ import annotations

import math
from collections import defaultdict
from typing import Sequence

import numpy as np

from lanevil_train.report.intervals import CONFIDENCE, REPLICATES

CLOSED_TYPES = ("yes_no", "choice")
ALL = "all"


def _scene(record: dict):
    return record.get("scene") or record["case_id"]


def _scene_weights(scenes: list, replicates: int, seed: int) -> np.ndarray:
    """Bootstrap weights [replicates, scenes]: each replicate draws the scenes with replacement."""
    rng = np.random.default_rng(seed)
    if not scenes:
        return np.zeros((replicates, 0))
    return rng.multinomial(len(scenes), np.full(len(scenes), 1.0 / len(scenes)), size=replicates).astype(float)


def _difference_interval(first: np.ndarray, second: np.ndarray, weights: np.ndarray,
                         confidence: float, scale: float = 100.0) -> tuple[float, float]:
    """The interval of accuracy(first) - accuracy(second) (x scale: 100, in %) over the weights' replicates; each
    table holds (correct, asked) per scene (or any (sum, count): a difference of means)."""
    alpha = (1 - confidence) / 2
    with np.errstate(invalid="ignore", divide="ignore"):
        diff = scale * ((weights @ first[:, 0]) / (weights @ first[:, 1])
                        - (weights @ second[:, 0]) / (weights @ second[:, 1]))
    diff = diff[np.isfinite(diff)]
    low, high = np.quantile(diff, [alpha, 1 - alpha]) if len(diff) else (math.nan, math.nan)
    return float(low), float(high)


def reliance_rows(model: list[dict], baselines: dict[str, list[dict]], order: Sequence[str] = (),
                  replicates: int = REPLICATES, confidence: float = CONFIDENCE, seed: int = 0) -> list[dict]:
    """One row per QA category present (in `order`, then as found; then "all"): for each closed type, n, the
    model's accuracy (%), each baseline's, the better baseline's name and the reliance with its interval (see the
    module docstring). Only the answers every one of them gave (same keys) count."""
    if not baselines:
        raise ValueError("visual reliance: expected at least one blind baseline (task.blind=grey, text or all)")
    keys = set.intersection({r["key"] for r in model}, *({r["key"] for r in rs} for rs in baselines.values()))
    runs = {"model": {r["key"]: r for r in model if r["key"] in keys},
            **{name: {r["key"]: r for r in rs if r["key"] in keys} for name, rs in baselines.items()}}
    scenes = sorted({_scene(r) for r in runs["model"].values()}, key=str)
    index = {s: i for i, s in enumerate(scenes)}
    weights = _scene_weights(scenes, replicates, seed)
    groups: dict[tuple[str, str], list[str]] = defaultdict(list)
    for key, r in runs["model"].items():
        if r["qa_type"] in CLOSED_TYPES:
            groups[r["qa_category"], r["qa_type"]].append(key)
            groups[ALL, r["qa_type"]].append(key)
    found = dict.fromkeys([*order, *(c for c, _ in groups if c != ALL), ALL])
    categories = [c for c in found if any((c, t) in groups for t in CLOSED_TYPES)]
    rows = []
    for category in categories:
        row: dict = {"qa_category": category}
        for kind in CLOSED_TYPES:
            members = groups.get((category, kind), [])
            row[f"{kind}/n"] = len(members)
            if not members:
                continue
            tables = {}
            for name, records in runs.items():
                table = np.zeros((len(scenes), 2))  # correct, asked per scene
                for key in members:
                    table[index[_scene(records[key])]] += (records[key]["correct"], 1)
                tables[name] = table
                row[f"{kind}/{name}"] = 100.0 * table[:, 0].sum() / table[:, 1].sum()
            best = max(baselines, key=lambda name: row[f"{kind}/{name}"])
            row[f"{kind}/best_baseline"] = best
            row[f"{kind}/reliance"] = row[f"{kind}/model"] - row[f"{kind}/{best}"]
            low, high = _difference_interval(tables["model"], tables[best], weights, confidence)
            row[f"{kind}/low"], row[f"{kind}/high"] = low, high
            row[f"{kind}/distinguishable"] = bool(low > 0 or high < 0)
        rows.append(row)
    return rows


def gap_rows(records: list[dict], order: Sequence[str] = (), replicates: int = REPLICATES,
             confidence: float = CONFIDENCE, seed: int = 0) -> list[dict]:
    """The illusion's accuracy Gap with its interval: one row per QA category present (in `order`, then as found;
    then "all"): n perturbed closed answers, their accuracy, the accuracy of the same questions on the clean clips
    (each clean answer counted once per perturbed answer it pairs with), Gap = perturbed - original and its 95 %
    interval from a paired bootstrap over the scenes."""
    clean = {r["qa_id"]: r for r in records if r["severity"] == 0 and r["qa_type"] in CLOSED_TYPES}
    pairs = [(r, clean[r["qa_id"]]) for r in records
             if r["severity"] != 0 and r["qa_type"] in CLOSED_TYPES and r["qa_id"] in clean]
    scenes = sorted({_scene(r) for r, _ in pairs}, key=str)
    index = {s: i for i, s in enumerate(scenes)}
    weights = _scene_weights(scenes, replicates, seed)
    groups: dict[str, list[tuple[dict, dict]]] = defaultdict(list)
    for pair in pairs:
        groups[pair[0]["qa_category"]].append(pair)
        groups[ALL].append(pair)
    rows = []
    for category in [c for c in dict.fromkeys([*order, *groups, ALL]) if c in groups]:
        perturbed, original = np.zeros((len(scenes), 2)), np.zeros((len(scenes), 2))
        for answer, twin in groups[category]:
            perturbed[index[_scene(answer)]] += (answer["correct"], 1)
            original[index[_scene(answer)]] += (twin["correct"], 1)
        accuracy = [100.0 * table[:, 0].sum() / table[:, 1].sum() for table in (perturbed, original)]
        low, high = _difference_interval(perturbed, original, weights, confidence)
        rows.append({"qa_category": category, "n": len(groups[category]), "perturbed": accuracy[0],
                     "original": accuracy[1], "gap": accuracy[0] - accuracy[1], "low": low, "high": high,
                     "distinguishable": bool(low > 0 or high < 0)})
    return rows


def gap_markdown(rows: list[dict]) -> str:
    lines = ["| QA category | n | Perturbed | Original | Gap [95 % CI] |", "|---|---|---|---|---|"]
    for row in rows:
        mark = " *" if row["distinguishable"] else ""
        lines.append(f"| {row['qa_category']} | {row['n']} | {row['perturbed']:.1f} | {row['original']:.1f} | "
                     f"{row['gap']:+.1f} [{row['low']:+.1f}, {row['high']:+.1f}]{mark} |")
    return "\n".join(lines) + "\n"


def reliance_markdown(rows: list[dict], baselines: list[str]) -> str:
    """The rows as a markdown table: per closed type, the model's accuracy, each baseline's and the reliance."""
    header = ["QA category"]
    for kind in CLOSED_TYPES:
        label = kind.replace("_", "/")
        header += [f"{label} n", f"{label} model", *(f"{label} {b}" for b in baselines),
                   f"{label} reliance [95 % CI]"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row in rows:
        cells = [row["qa_category"]]
        for kind in CLOSED_TYPES:
            if not row.get(f"{kind}/n"):
                cells += ["0", "", *("" for _ in baselines), ""]
                continue
            mark = " *" if row[f"{kind}/distinguishable"] else ""
            cells += [str(row[f"{kind}/n"]), f"{row[f'{kind}/model']:.1f}",
                      *(f"{row[f'{kind}/{b}']:.1f}" for b in baselines),
                      f"{row[f'{kind}/reliance']:+.1f} [{row[f'{kind}/low']:+.1f}, {row[f'{kind}/high']:+.1f}]"
                      f" vs {row[f'{kind}/best_baseline']}{mark}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
