"""Headline scores from per-item records: the spec's summary scores per (model, dataset, original|perturbed)
group (TuSimple Accuracy/FP/FN/F1 and F1_count, and CULane F1 where counted, for lane detectors)."""

from __future__ import annotations

from collections import defaultdict

from lanevil_train.report.records import available_scores
from lanevil_train.report.specs import spec_for


def summarise(records: list[dict], spec=None) -> dict:
    """Scores of a group of per-item records: the item count, then each summary score the records support."""
    spec = spec or spec_for(records)
    row = {spec.count_name: len(records)}
    row.update({s.name: s.aggregate(records) for s in available_scores(records, spec.summary_scores())})
    return row


def summary_rows(records: list[dict], spec=None) -> list[dict]:
    """One row per (model, dataset, original|perturbed) group, in first-seen order."""
    spec = spec or spec_for(records)
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for record in records:
        kind = "original" if record.get("severity", 0) == 0 else "perturbed"
        groups[(record.get("model", ""), record.get("dataset", ""), kind)].append(record)
    return [{"model": m, "dataset": d, f"{spec.count_name}_kind": k, **summarise(rs, spec)}
            for (m, d, k), rs in groups.items()]
