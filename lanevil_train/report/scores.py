"""Headline scores from per-image records: TuSimple Accuracy/FP/FN/F1 (and CULane F1) per group."""

from __future__ import annotations

from collections import defaultdict

from lanevil_train.metrics import tusimple_summary


def summarise(records: list[dict]) -> dict:
    """Scores (%) of a group of per-image records: images, Accuracy, FP, FN, F1 (+ CULane_F1 if counted)."""
    n = len(records)
    tusimple = tusimple_summary(sum(r["accuracy"] for r in records), sum(r["fp"] for r in records),
                                sum(r["fn"] for r in records), n)
    row = {"images": n, **{key: 100.0 * float(tusimple[key]) for key in ("Accuracy", "FP", "FN", "F1")}}
    if records and all("culane_tp" in r for r in records):
        tp, fp, fn = (sum(r[k] for r in records) for k in ("culane_tp", "culane_fp", "culane_fn"))
        row["CULane_F1"] = 100.0 * 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else 0.0
    return row


def summary_rows(records: list[dict]) -> list[dict]:
    """One row per (model, dataset, original|perturbed) group, in first-seen order."""
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for record in records:
        kind = "original" if record.get("severity", 0) == 0 else "perturbed"
        groups[(record.get("model", ""), record.get("dataset", ""), kind)].append(record)
    return [{"model": m, "dataset": d, "images_kind": k, **summarise(rs)} for (m, d, k), rs in groups.items()]
