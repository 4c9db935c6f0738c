"""Robustness tables from per-image scores: the paper's Perturbed / Original / Gap layout and relative measures.

Input is a list of plain per-image records (one dict per scored image)::

    {"model", "dataset", "case_id", "illusion", "category", "severity" (0 = clean original, 1..5 perturbed),
     "accuracy", "fp", "fn" (TuSimple per-image scores in [0, 1]), optional "image", "pred_lanes", "gt_lanes"}

Conventions (all scores in %):
- Accuracy = 100 * mean(accuracy); F1 = 100 * ``tusimple_summary`` F1 from the mean fp / fn of the same images.
- Perturbed = all perturbed images of the group, pooled (each image weighs the same, over types and severities).
- Original = the clean (severity 0) images of THE SAME CASES, i.e. the (dataset, case_id) pairs that have a
  perturbed image in the group; each case's clean image counts once.
- Gap = Perturbed - Original (a model that does worse under the illusion has a negative gap).
- "average" = the unweighted mean of the per-category values over the categories present (Gap included, so
  average Gap = average Perturbed - average Original). The paper's Average column is not the mean of its four
  category columns (e.g. LaneATT: 76.23, 73.18, 79.48, 71.33 -> 75.06, reported 73.53), so it is some weighted
  mean it does not define; ours is stated here and reproducible.
"""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

from lanevil_train.metrics import tusimple_summary
from lanevil_train.report.tables import markdown_table, write_table

# category -> illusion names in the paper's order (mirrors lanevil_train.illusions.registry.CATEGORIES, which
# report/ may not import); used only to order rows/columns and to fill a missing category from the illusion.
CATEGORIES: dict[str, tuple[str, ...]] = {
    "road_damage": ("road_crack", "road_repair", "tire_marks", "guard_rail"),
    "traffic_obstruction": ("pedestrian", "vehicle", "bicycle"),
    "shadow": ("streetlight_shadow", "fence_shadow", "rail_shadow", "wire_shadow"),
    "reflection": ("sunlight_reflection", "streetlight_reflection", "vehicle_reflection"),
}
ILLUSION_CATEGORY: dict[str, str] = {name: cat for cat, names in CATEGORIES.items() for name in names}
SEVERITIES = (1, 2, 3, 4, 5)
_REQUIRED = ("model", "dataset", "case_id", "severity", "accuracy", "fp", "fn")
NAN = float("nan")


# ----------------------------------------------------------------------------------------------- records
# Ranges of the official TuSimple per-image scores. Accuracy can exceed 1 with more than 5 GT lanes (it
# drops the worst lane but divides by 4: up to 5/4 with the 6 lanes of a simulated 5-lane road), and FP
# can be negative (one prediction may match several GT lanes, e.g. short ones mostly outside the image).
_RANGE = {"accuracy": (0.0, 1.25), "fp": (-float("inf"), 1.0), "fn": (0.0, 1.0)}


def validate_records(records: list[dict]) -> list[dict]:
    """Check and normalise records (fill a missing category from a known illusion); raise naming the bad record."""
    if not isinstance(records, (list, tuple)):
        raise TypeError(f"records must be a list of dicts, got {type(records).__name__}")
    out, clean_seen, pert_seen = [], {}, set()
    for i, rec in enumerate(records):
        if not isinstance(rec, dict):
            raise TypeError(f"record {i}: expected a dict, got {type(rec).__name__}")
        missing = [k for k in _REQUIRED if k not in rec or rec[k] is None]
        if missing:
            raise ValueError(f"record {i}: missing required key(s) {missing}; expected keys {list(_REQUIRED)}")
        sev = rec["severity"]
        if isinstance(sev, bool) or not isinstance(sev, int) or not 0 <= sev <= 5:
            raise ValueError(f"record {i}: severity must be an int in 0..5 (0 = clean), got {sev!r}")
        for key in ("accuracy", "fp", "fn"):
            val, (low, top) = rec[key], _RANGE[key]
            if isinstance(val, bool) or not isinstance(val, (int, float)) or not low <= float(val) <= top:
                raise ValueError(f"record {i}: {key} must be a number in [{low}, {top}], got {val!r}")
        norm = dict(rec)
        norm["model"], norm["dataset"], norm["case_id"] = str(rec["model"]), str(rec["dataset"]), str(rec["case_id"])
        for key in ("accuracy", "fp", "fn"):
            norm[key] = float(rec[key])
        case = (norm["model"], norm["dataset"], norm["case_id"])
        if sev == 0:
            scores = (norm["accuracy"], norm["fp"], norm["fn"])
            if case in clean_seen:
                if clean_seen[case] != scores:
                    raise ValueError(f"record {i}: a second clean (severity 0) record for model/dataset/case {case} "
                                     f"with different scores {scores} vs {clean_seen[case]}")
                continue  # the same clean image written once per illusion: count it once
            clean_seen[case] = scores
        else:
            illusion = rec.get("illusion")
            if not illusion:
                raise ValueError(f"record {i}: a perturbed record (severity {sev}) needs an 'illusion' name")
            category = rec.get("category") or ILLUSION_CATEGORY.get(illusion)
            if not category:
                raise ValueError(f"record {i}: perturbed record of unknown illusion {illusion!r} has no 'category'")
            norm["illusion"], norm["category"] = str(illusion), str(category)
            key = case + (norm["illusion"], sev)
            if key in pert_seen:
                raise ValueError(f"record {i}: duplicate perturbed record for (model, dataset, case_id, illusion, "
                                 f"severity) {key}")
            pert_seen.add(key)
        out.append(norm)
    return out


def scores(recs: list[dict]) -> tuple[float, float]:
    """(Accuracy %, F1 %) of a set of per-image records; NaN for an empty set."""
    if not recs:
        return NAN, NAN
    summary = tusimple_summary(sum(r["accuracy"] for r in recs), sum(r["fp"] for r in recs),
                               sum(r["fn"] for r in recs), len(recs))
    return 100.0 * summary["Accuracy"], 100.0 * summary["F1"]


def _ordered(values, order) -> list[str]:
    present = set(values)
    return [v for v in order if v in present] + sorted(present - set(order))


def _models(recs: list[dict]) -> list[str]:
    return list(dict.fromkeys(r["model"] for r in recs))


class _Index:
    """Records of one model split into clean-by-case and perturbed."""

    def __init__(self, recs: list[dict], model: str):
        self.model = model
        self.clean = {(r["dataset"], r["case_id"]): r for r in recs if r["severity"] == 0}
        self.pert = [r for r in recs if r["severity"] > 0]

    def originals(self, pert: list[dict]) -> list[dict]:
        """The clean records of the cases that have images in `pert` (each once); raise if one is missing."""
        cases = dict.fromkeys((r["dataset"], r["case_id"]) for r in pert)
        missing = [c for c in cases if c not in self.clean]
        if missing:
            raise ValueError(f"model {self.model!r}: no clean (severity 0) record for {len(missing)} case(s) with "
                             f"perturbed images, e.g. (dataset, case_id) {missing[0]}; Original needs the same cases")
        return [self.clean[c] for c in cases]

    def pog(self, pert: list[dict]) -> dict[str, float]:
        """Perturbed / Original / Gap for Accuracy and F1 of a group of perturbed records."""
        p_acc, p_f1 = scores(pert)
        o_acc, o_f1 = scores(self.originals(pert)) if pert else (NAN, NAN)
        return {"Accuracy/Perturbed": p_acc, "Accuracy/Original": o_acc, "Accuracy/Gap": p_acc - o_acc,
                "F1/Perturbed": p_f1, "F1/Original": o_f1, "F1/Gap": p_f1 - o_f1}


def _indexes(records: list[dict]) -> tuple[list[str], list[dict], dict[str, _Index]]:
    recs = validate_records(records)
    models = _models(recs)
    by_model = defaultdict(list)
    for r in recs:
        by_model[r["model"]].append(r)
    return models, recs, {m: _Index(by_model[m], m) for m in models}


def _mean(values) -> float:
    vals = [v for v in values if not math.isnan(v)]
    return sum(vals) / len(vals) if vals else NAN


# ------------------------------------------------------------------------------------------------ tables
def main_table(records: list[dict]) -> list[dict]:
    """One row per model: Perturbed / Original / Gap (Accuracy, F1) per category and on average (paper layout)."""
    models, recs, idx = _indexes(records)
    cats = _ordered((r["category"] for r in recs if r["severity"] > 0), CATEGORIES)
    rows = []
    for m in models:
        row, per_cat = {"model": m}, []
        for cat in cats:
            vals = idx[m].pog([r for r in idx[m].pert if r["category"] == cat])
            per_cat.append(vals)
            row.update({f"{cat}/{k}": v for k, v in vals.items()})
        for k in ("Accuracy/Perturbed", "Accuracy/Original", "Accuracy/Gap", "F1/Perturbed", "F1/Original", "F1/Gap"):
            row[f"average/{k}"] = _mean(v[k] for v in per_cat)
        rows.append(row)
    return rows


def type_table(records: list[dict]) -> list[dict]:
    """Rows (model, illusion): Perturbed / Original / Gap for Accuracy and F1 over all that type's severities."""
    models, recs, idx = _indexes(records)
    order = [n for names in CATEGORIES.values() for n in names]
    illusions = _ordered((r["illusion"] for r in recs if r["severity"] > 0), order)
    rows = []
    for m in models:
        for ill in illusions:
            pert = [r for r in idx[m].pert if r["illusion"] == ill]
            if pert:
                rows.append({"model": m, "category": pert[0]["category"], "illusion": ill, **idx[m].pog(pert)})
    return rows


def severity_table(records: list[dict]) -> list[dict]:
    """Rows (model, category, severity 1..5): Accuracy and F1, with the same cases' Original and the Gap."""
    models, recs, idx = _indexes(records)
    cats = _ordered((r["category"] for r in recs if r["severity"] > 0), CATEGORIES)
    rows = []
    for m in models:
        for cat in cats:
            for sev in SEVERITIES:
                pert = [r for r in idx[m].pert if r["category"] == cat and r["severity"] == sev]
                if pert:
                    v = idx[m].pog(pert)
                    rows.append({"model": m, "category": cat, "severity": sev, "images": len(pert),
                                 "Accuracy": v["Accuracy/Perturbed"], "F1": v["F1/Perturbed"],
                                 "Accuracy/Original": v["Accuracy/Original"], "F1/Original": v["F1/Original"],
                                 "Accuracy/Gap": v["Accuracy/Gap"], "F1/Gap": v["F1/Gap"]})
    return rows


def _type_severity_acc(index: _Index) -> dict[str, dict]:
    """illusion -> {"category", "orig": Original accuracy %, "sev": {severity: accuracy %}}."""
    out = {}
    for ill in dict.fromkeys(r["illusion"] for r in index.pert):
        pert = [r for r in index.pert if r["illusion"] == ill]
        out[ill] = {"category": pert[0]["category"], "orig": scores(index.originals(pert))[0],
                    "sev": {s: scores([r for r in pert if r["severity"] == s])[0]
                            for s in sorted({r["severity"] for r in pert})}}
    return out


def _ratio(num: float, den: float) -> float:
    return num / den if den != 0 and not math.isnan(den) else NAN


def relative_table(records: list[dict], baseline: str | None = None) -> list[dict]:
    """Per model: relative robustness (Perturbed / Original accuracy, %) per category and average; with a
    baseline model also mCE and relative mCE (Hendrycks & Dietterich 2019) over illusion types, in %.

    CE_type = sum_s (100 - Acc_s) / sum_s (100 - Acc_base,s); relative CE_type = sum_s (Acc_orig - Acc_s) /
    sum_s (Acc_base,orig - Acc_base,s), where Acc_orig is the type's Original (same cases' clean images) and
    s runs over the severities both models have. mCE = 100 * mean over types (those both models have);
    "<category>/CE" = 100 * mean over that category's types. A zero denominator gives NaN.
    """
    models, recs, idx = _indexes(records)
    main = {row["model"]: row for row in main_table(records)}
    cats = _ordered((r["category"] for r in recs if r["severity"] > 0), CATEGORIES)
    if baseline is not None and baseline not in idx:
        raise ValueError(f"baseline model {baseline!r} not among the records' models {models}")
    base = _type_severity_acc(idx[baseline]) if baseline is not None else None
    rows = []
    for m in models:
        row = {"model": m}
        rel = []
        for cat in cats:
            v = _ratio(main[m][f"{cat}/Accuracy/Perturbed"], main[m][f"{cat}/Accuracy/Original"]) * 100.0
            row[f"{cat}/RelRobustness"] = v
            rel.append(v)
        row["average/RelRobustness"] = _mean(rel)
        if base is not None:
            own = _type_severity_acc(idx[m])
            ce, rce = {}, {}
            for ill, b in base.items():
                if ill not in own:
                    continue
                sevs = [s for s in b["sev"] if s in own[ill]["sev"]]
                a = own[ill]
                ce[ill] = _ratio(sum(100.0 - a["sev"][s] for s in sevs), sum(100.0 - b["sev"][s] for s in sevs))
                rce[ill] = _ratio(sum(a["orig"] - a["sev"][s] for s in sevs), sum(b["orig"] - b["sev"][s] for s in sevs))
            for cat in cats:
                row[f"{cat}/CE"] = 100.0 * _mean(v for k, v in ce.items() if base[k]["category"] == cat)
            row["mCE"] = 100.0 * _mean(ce.values())
            row["relative_mCE"] = 100.0 * _mean(rce.values())
        rows.append(row)
    return rows


# ------------------------------------------------------------------------------------------------ report
def write_report(records: list[dict], out_dir: str | Path, baseline: str | None = None) -> dict[str, Path]:
    """Write every table (md/csv/json), a combined report.md and the PNG plots into out_dir; return the paths."""
    from lanevil_train.report import plots  # matplotlib only when plotting

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    tables = {"main": main_table(records), "per_type": type_table(records),
              "per_severity": severity_table(records), "relative": relative_table(records, baseline)}
    paths: dict[str, Path] = {}
    for name, rows in tables.items():
        for fmt, p in write_table(rows, out_dir, name).items():
            paths[f"{name}_{fmt}"] = p
    titles = {"main": "Robustness per category (Perturbed / Original / Gap = Perturbed - Original, %)",
              "per_type": "Per illusion type", "per_severity": "Per severity level",
              "relative": "Relative robustness (Perturbed / Original accuracy, %)"
                          + (f"; mCE vs baseline {baseline!r}" if baseline else "")}
    parts = ["# Robustness report", "",
             "Accuracy and F1 in %; Original = the clean images of the same cases; average = mean of the "
             "category values.", ""]
    for name, rows in tables.items():
        parts += [f"## {titles[name]}", "", markdown_table(rows), ""]
    for name, fn in (("accuracy_vs_severity", plots.accuracy_vs_severity), ("gap_heatmap", plots.gap_heatmap),
                     ("worst_cases", plots.worst_cases)):
        p = fn(records, out_dir / f"{name}.png")
        if p is not None:
            paths[name] = Path(p)
            parts += [f"![{name}]({Path(p).name})", ""]
    paths["report"] = out_dir / "report.md"
    paths["report"].write_text("\n".join(parts))
    return paths
