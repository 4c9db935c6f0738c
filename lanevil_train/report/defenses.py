"""Defense comparison (the paper's Fig. enhance): each defense's perturbed Accuracy / F1 per illusion category
and on average, its clean (original) scores, and its GAIN over the undefended reference (`none`).

Input: {defense name: that defense's per-image robustness records} (see report/robustness.py for a record).
Conventions (all in %, gains in percentage points):
- per category: the pooled perturbed images of the category (report.robustness.main_table "Perturbed");
- average: the unweighted mean of the category values (main_table's "average");
- original: all clean (severity 0) images of the suite, each case once (a defense that costs clean accuracy
  shows a negative original gain);
- gain = defense - reference, per category, average and original. Every defense must be scored on the same
  images as the reference (same cases, illusions and severities), else the gains would compare different tests.
"""

from __future__ import annotations

import math
from pathlib import Path

from lanevil_train.report.robustness import CATEGORIES, _ordered, main_table, scores, validate_records
from lanevil_train.report.tables import markdown_table, write_table

REFERENCE = "none"
AVERAGE = "average"
ORIGINAL = "original"
METRICS = ("Accuracy", "F1")


def _image_keys(recs: list[dict]) -> set[tuple]:
    """The scored images of validated records: (dataset, case, illusion or None when clean, severity)."""
    return {(r["dataset"], r["case_id"], r.get("illusion") if r["severity"] else None, r["severity"]) for r in recs}


def check_comparable(records_by_defense: dict[str, list[dict]], reference: str = REFERENCE) -> dict[str, list[dict]]:
    """Validate each defense's records (one model each, perturbed images present, the reference's image set);
    return them validated. Raises ValueError naming the defense at fault."""
    if not records_by_defense:
        raise ValueError("no defenses to compare: records_by_defense is empty")
    if reference not in records_by_defense:
        raise ValueError(f"the reference defense {reference!r} is missing (defenses given: "
                         f"{list(records_by_defense)}); gains are measured against it, so it must be compared too")
    out = {}
    for defense, recs in records_by_defense.items():
        try:
            valid = validate_records(list(recs))
        except (TypeError, ValueError) as err:
            raise ValueError(f"defense {defense!r}: {err}") from err
        models = sorted({r["model"] for r in valid})
        if len(models) != 1:
            raise ValueError(f"defense {defense!r}: expected the records of one model, got {models or 'none'}")
        if not any(r["severity"] > 0 for r in valid):
            raise ValueError(f"defense {defense!r}: no perturbed (severity > 0) records; was it scored on a suite?")
        out[defense] = valid
    ref_keys = _image_keys(out[reference])
    for defense, recs in out.items():
        keys = _image_keys(recs)
        if keys != ref_keys:
            raise ValueError(f"defense {defense!r} was scored on different images than {reference!r}: "
                             f"{len(keys - ref_keys)} image(s) only in {defense!r}, {len(ref_keys - keys)} only in "
                             f"{reference!r}; compare runs scored on the same suite (cases, illusions, severities)")
    return out


def defense_scores(records_by_defense: dict[str, list[dict]], reference: str = REFERENCE) -> list[dict]:
    """One row per defense (input order): its model label, clean scores ("original/..."), perturbed Accuracy and
    F1 per category and on average ("<category>/Accuracy", "average/F1", ...), and the perturbed image count."""
    valid = check_comparable(records_by_defense, reference)
    rows = []
    for defense, recs in valid.items():
        main = main_table(recs)[0]
        cats = _ordered((r["category"] for r in recs if r["severity"] > 0), CATEGORIES)
        clean_acc, clean_f1 = scores([r for r in recs if r["severity"] == 0])
        row = {"defense": defense, "model": recs[0]["model"],
               "images": sum(r["severity"] > 0 for r in recs),
               f"{ORIGINAL}/Accuracy": clean_acc, f"{ORIGINAL}/F1": clean_f1}
        for cat in [*cats, AVERAGE]:
            for metric in METRICS:
                row[f"{cat}/{metric}"] = main[f"{cat}/{metric}/Perturbed"]
        rows.append(row)
    return rows


def _groups(score_row: dict) -> list[str]:
    """The column groups of a defense_scores row: categories, then average, then original."""
    groups = list(dict.fromkeys(key.split("/")[0] for key in score_row if "/" in key))
    return [g for g in groups if g != ORIGINAL] + [g for g in groups if g == ORIGINAL]


def defense_gain(score_rows: list[dict], reference: str = REFERENCE) -> list[dict]:
    """Long table, one row per (defense other than the reference, category | average | original): the defense's
    score, the reference's, and the gain (defense - reference, points) for Accuracy and F1."""
    by_name = {row["defense"]: row for row in score_rows}
    if reference not in by_name:
        raise ValueError(f"the reference defense {reference!r} is not among the scored defenses {list(by_name)}")
    ref = by_name[reference]
    rows = []
    for row in score_rows:
        if row["defense"] == reference:
            continue
        for group in _groups(row):
            out = {"defense": row["defense"], "category": group}
            for metric in METRICS:
                key = f"{group}/{metric}"
                out[metric] = row[key]
                out[f"{metric}/{reference}"] = ref.get(key, math.nan)
                out[f"{metric}/gain"] = row[key] - ref.get(key, math.nan)
            rows.append(out)
    return rows


def gain_pivot(gain_rows: list[dict], metric: str = "Accuracy") -> list[dict]:
    """The gain table as one row per defense and one column per category (then average, original): the figure."""
    out: dict[str, dict] = {}
    for row in gain_rows:
        out.setdefault(row["defense"], {"defense": row["defense"]})[row["category"]] = row[f"{metric}/gain"]
    return list(out.values())


def best_defense(score_rows: list[dict]) -> tuple[str, float]:
    """The defense with the highest average perturbed Accuracy (reference included; NaN rows ignored)."""
    ranked = [(row["average/Accuracy"], row["defense"]) for row in score_rows
              if not math.isnan(row["average/Accuracy"])]
    if not ranked:
        raise ValueError("no defense has an average perturbed Accuracy")
    value, name = max(ranked, key=lambda t: t[0])  # max keeps the first of equal values: input order
    return name, value


def gain_plot(gain_rows: list[dict], path: str | Path, metric: str = "Accuracy") -> Path:
    """Grouped bars: x = category and average, one bar per defense, y = gain over the reference in points."""
    from lanevil_train.report.plots import save_figure  # sets the Agg backend

    import matplotlib.pyplot as plt

    pivot = gain_pivot(gain_rows, metric)
    groups = [g for g in dict.fromkeys(r["category"] for r in gain_rows) if g != ORIGINAL]
    n = max(len(pivot), 1)
    width = 0.8 / n
    fig, ax = plt.subplots(figsize=(1.6 + 1.3 * max(len(groups), 1), 3.8))
    for i, row in enumerate(pivot):
        xs = [j - 0.4 + width * (i + 0.5) for j in range(len(groups))]
        ax.bar(xs, [row.get(g, math.nan) for g in groups], width, label=row["defense"])
    ax.axhline(0.0, color="black", linewidth=0.8)
    ax.set_xticks(range(len(groups)), [g.replace("_", "\n") for g in groups], fontsize=8)
    ax.set_ylabel(f"{metric} gain over none (points)")
    ax.set_title(f"Defense gain in perturbed {metric} over no defense")
    ax.grid(axis="y", alpha=0.3)
    if pivot:
        ax.legend(fontsize=7, ncol=min(n, 4))
    return save_figure(fig, path)


def write_defense_report(score_rows: list[dict], gain_rows: list[dict], out_dir: str | Path,
                         runs: dict[str, str] | None = None) -> dict[str, Path]:
    """defense_scores.{md,csv,json}, defense_gain.{md,csv,json}, defense_gain.png and compare.md in out_dir.

    `runs` (defense -> run directory) is listed in compare.md when given.
    """
    out_dir = Path(out_dir)
    paths: dict[str, Path] = {}
    for name, rows in (("defense_scores", score_rows), ("defense_gain", gain_rows)):
        for fmt, p in write_table(rows, out_dir, name).items():
            paths[f"{name}_{fmt}"] = p
    paths["plot"] = gain_plot(gain_rows, out_dir / "defense_gain.png")
    best, value = best_defense(score_rows)
    parts = ["# Defense comparison", "",
             "Scores in %, gains in percentage points (defense minus none) on the same illusion suite. Per "
             "category: all perturbed images of the category; average: mean of the categories; original: the "
             "suite's clean images (a negative original gain is a cost in clean accuracy).", "",
             f"Best average perturbed Accuracy: **{best}** ({value:.2f}%).", "",
             "## Accuracy gain over none (points)", "", markdown_table(gain_pivot(gain_rows, "Accuracy")), "",
             "## F1 gain over none (points)", "", markdown_table(gain_pivot(gain_rows, "F1")), "",
             f"![defense gain]({paths['plot'].name})", "",
             "## Scores per defense (perturbed per category and average; original = clean)", "",
             markdown_table(score_rows), "",
             "Long form with each side of every gain: defense_gain.md / .csv / .json.", ""]
    if runs:
        parts += ["## Runs", "", markdown_table([{"defense": d, "run": str(r)} for d, r in runs.items()]), ""]
    paths["report"] = out_dir / "compare.md"
    paths["report"].write_text("\n".join(parts))
    return paths
