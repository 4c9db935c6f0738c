"""Robustness tables from per-item records: the paper's Perturbed / Original / Gap layout and relative measures.

Records and their conventions are described in report/records.py; the scores come from the records' spec
(report/specs.py: TuSimple Accuracy, the papers' F1 and the lane-count F1_count for lane detectors). Every table
takes a list of records (the spec is inferred) or a RecordSet. The paper's Average column is not the mean of its
four category columns (e.g. LaneATT: 76.23, 73.18, 79.48, 71.33 -> 75.06, reported 73.53), so it is some weighted
mean it does not define; ours, the mean of the category values, is stated and reproducible.
"""

from __future__ import annotations

import math
from pathlib import Path

from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.report.records import AVERAGE, KINDS, NAN, ModelRecords, RecordSet, mean
from lanevil_train.report.specs import record_set
from lanevil_train.report.tables import markdown_table, write_table


def main_table(records) -> list[dict]:
    """One row per model: Perturbed / Original / Gap of every score per category and on average (paper layout)."""
    rs = record_set(records)
    rows = []
    for m in rs.models:
        row, per_cat = {"model": m}, []
        groups = {cat: pert for (cat,), pert in rs.groups(m, ("category",))}
        for cat in rs.categories:  # every model gets every column; a category it lacks is NaN
            values = rs.by_model[m].pog(groups.get(cat, []), rs.scores)
            per_cat.append(values)
            row.update({f"{cat}/{k}": v for k, v in values.items()})
        for score in rs.scores:
            for kind in KINDS:
                key = f"{score.name}/{kind}"
                row[f"{AVERAGE}/{key}"] = mean(v[key] for v in per_cat)
        rows.append(row)
    return rows


def type_table(records) -> list[dict]:
    """Rows (model, illusion): Perturbed / Original / Gap of every score over all that type's severities."""
    rs = record_set(records)
    return [{"model": m, "category": cat, "illusion": ill, **rs.by_model[m].pog(pert, rs.scores)}
            for m in rs.models for (cat, ill), pert in rs.groups(m, ("category", "illusion"))]


def severity_table(records) -> list[dict]:
    """Rows (model, category, severity 1..5): every score, then each with the same items' Original, then Gap."""
    rs = record_set(records)
    rows = []
    for m in rs.models:
        for (cat, sev), pert in rs.groups(m, ("category", "severity")):
            values = rs.by_model[m].pog(pert, rs.scores)
            row = {"model": m, "category": cat, "severity": sev, rs.spec.count_name: len(pert)}
            row.update({s.name: values[f"{s.name}/Perturbed"] for s in rs.scores})
            row.update({f"{s.name}/{kind}": values[f"{s.name}/{kind}"] for kind in ("Original", "Gap")
                        for s in rs.scores})
            rows.append(row)
    return rows


def group_table(records, field: str) -> list[dict]:
    """Rows (model, value of `field`, e.g. a QA category): Perturbed / Original / Gap over all perturbed records
    with that value (records without the field are left out)."""
    rs = record_set(records)
    return [{"model": m, field: value, rs.spec.count_name: len(pert), **rs.by_model[m].pog(pert, rs.scores)}
            for m in rs.models for (value,), pert in rs.groups(m, (field,)) if value is not None]


def _type_severity(index: ModelRecords, rs: RecordSet) -> dict[str, dict]:
    """illusion -> {"category", "orig": the headline score's Original, "sev": {severity: headline score}}."""
    score = rs.headline
    out = {}
    for (cat, ill), pert in rs.groups(index.model, ("category", "illusion")):
        by_sev = {}
        for r in pert:
            by_sev.setdefault(r["severity"], []).append(r)
        out[ill] = {"category": cat, "orig": score.aggregate(index.originals(pert)),
                    "sev": {s: score.aggregate(by_sev[s]) for s in sorted(by_sev)}}
    return out


def _ratio(num: float, den: float) -> float:
    return num / den if den != 0 and not math.isnan(den) else NAN


def relative_table(records, baseline: str | None = None) -> list[dict]:
    """Per model, on the headline score (Accuracy for lanes): relative robustness per category and average; with a
    baseline model also mCE and relative mCE (Hendrycks & Dietterich 2019) over illusion types, in %.

    For a higher-is-better score S in %: RelRobustness = 100 * Perturbed / Original; error E = 100 - S; for a
    lower-is-better one: RelRobustness = 100 * Original / Perturbed; E = S. CE_type = sum_s E_s / sum_s E_base,s;
    relative CE_type = sum_s (E_s - E_orig) / sum_s (E_base,s - E_base,orig), where orig is the type's Original
    (same items' clean records) and s runs over the severities both models have. mCE = 100 * mean over types
    (those both models have); "<category>/CE" = 100 * mean over that category's types. A zero denominator
    gives NaN.
    """
    rs = record_set(records)
    higher = rs.headline.higher_is_better
    name = rs.headline.name
    main = {row["model"]: row for row in main_table(rs)}
    if baseline is not None and baseline not in rs.by_model:
        raise ValueError(f"baseline model {baseline!r} not among the records' models {rs.models}")

    def error(value: float) -> float:
        return 100.0 - value if higher else value

    base = _type_severity(rs.by_model[baseline], rs) if baseline is not None else None
    rows = []
    for m in rs.models:
        row, rel = {"model": m}, []
        for cat in rs.categories:
            p, o = main[m].get(f"{cat}/{name}/Perturbed", NAN), main[m].get(f"{cat}/{name}/Original", NAN)
            v = 100.0 * (_ratio(p, o) if higher else _ratio(o, p))
            row[f"{cat}/RelRobustness"] = v
            rel.append(v)
        row[f"{AVERAGE}/RelRobustness"] = mean(rel)
        if base is not None:
            own = _type_severity(rs.by_model[m], rs)
            ce, rce = {}, {}
            for ill, b in base.items():
                if ill not in own:
                    continue
                a = own[ill]
                sevs = [s for s in b["sev"] if s in a["sev"]]
                ce[ill] = _ratio(sum(error(a["sev"][s]) for s in sevs), sum(error(b["sev"][s]) for s in sevs))
                rce[ill] = _ratio(sum(error(a["sev"][s]) - error(a["orig"]) for s in sevs),
                                  sum(error(b["sev"][s]) - error(b["orig"]) for s in sevs))
            for cat in rs.categories:
                row[f"{cat}/CE"] = 100.0 * mean(v for k, v in ce.items() if base[k]["category"] == cat)
            row["mCE"] = 100.0 * mean(ce.values())
            row["relative_mCE"] = 100.0 * mean(rce.values())
        rows.append(row)
    return rows


def main_long(main_rows: list[dict]) -> list[dict]:
    """The paper-layout table (one wide row per model) as one row per (model, category), for a console."""
    out = []
    for row in main_rows:
        cells: dict[str, dict] = {}
        for key, value in row.items():
            if key.count("/") == 2:
                group, score, kind = key.split("/")
                cells.setdefault(group, {})[f"{score} {kind}"] = value
        out += [{"model": row["model"], "category": group, **values} for group, values in cells.items()]
    return out


# ------------------------------------------------------------------------------------------------ report
def write_report(records, out_dir: str | Path, baseline: str | None = None) -> dict[str, Path]:
    """Write every table (md/csv/json), a combined report.md and the PNG plots into out_dir; return the paths."""
    from lanevil_train.report import plots  # matplotlib only when plotting

    rs = record_set(records)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    headline = rs.headline.name
    tables = {"main": main_table(rs), "per_type": type_table(rs), "per_severity": severity_table(rs)}
    titles = {"main": f"Robustness per category (Perturbed / Original / Gap = Perturbed - Original, {rs.spec.unit})",
              "per_type": "Per illusion type", "per_severity": "Per severity level"}
    for field in rs.spec.groups:
        tables[f"per_{field}"] = group_table(rs, field)
        titles[f"per_{field}"] = f"Per {field.replace('_', ' ')}"
    tables["relative"] = relative_table(rs, baseline)
    titles["relative"] = (f"Relative robustness ({headline}: Perturbed vs Original, %)"
                          + (f"; mCE vs baseline {baseline!r}" if baseline else ""))
    from lanevil_train.report.combined import combined_markdown, combined_table, pair_categories

    if pair_categories(rs):
        tables["combined"] = combined_table(rs)
    paths: dict[str, Path] = {}
    for name, rows in tables.items():
        for fmt, p in write_table(rows, out_dir, name).items():
            paths[f"{name}_{fmt}"] = p
    lower = [s.name for s in rs.scores if not s.higher_is_better]
    parts = ["# Robustness report", "",
             f"{', '.join(s.name for s in rs.scores)} in {rs.spec.unit}; Original = the clean records of the same "
             f"items; average = mean of the category values."
             + (f" Lower is better for {', '.join(lower)}." if lower else ""), ""]
    for name, rows in tables.items():
        if name == "combined":
            parts += [f"## Combined illusions ({headline}, {rs.spec.unit}; paper Table combined): each pair's "
                      "Perturbed, Original and Gap, each of its illusions alone on the same cases and severities, "
                      "and the pair's Gap against each", "", combined_markdown(rows, headline), ""]
            continue
        parts += [f"## {titles[name]}", "", markdown_table(rows), ""]
    figures = {f"{headline.lower()}_vs_severity": plots.score_vs_severity, "gap_heatmap": plots.gap_heatmap,
               "worst_cases": plots.worst_cases}
    for name, fn in figures.items():
        p = fn(rs, out_dir / f"{name}.png")
        if p is not None:
            paths[name] = Path(p)
            parts += [f"![{name}]({Path(p).name})", ""]
    paths["report"] = out_dir / "report.md"
    atomic_write_text(paths["report"], "\n".join(parts))
    return paths
