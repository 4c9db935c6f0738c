"""Defense comparison (the paper's Fig. enhance): each defense's perturbed scores (the records' spec: Accuracy and
F1 for lanes) per illusion category and on average, its clean (original) scores, and its GAIN over the undefended
reference (`none`).

Input: {defense name: that defense's per-item robustness records} (see report/records.py for a record).
Conventions (all in the spec's unit, gains in its points; for a lower-is-better score a negative gain is good):
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

from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.report.records import AVERAGE, RecordSet, RecordSpec, item_of
from lanevil_train.report.robustness import main_table
from lanevil_train.report.specs import spec_for
from lanevil_train.report.tables import markdown_table, write_table

REFERENCE = "none"
ORIGINAL = "original"


def _item_keys(rs: RecordSet) -> set[tuple]:
    """The scored items of a record set: (dataset, case, [item,] illusion or None when clean, severity)."""
    return {item_of(r, rs.spec)[1:] + (r.get("illusion") if r["severity"] else None, r["severity"])
            for r in rs.records}


def as_seeds(records_by_defense: dict) -> dict[str, dict[int, list[dict]]]:
    """{defense: {seed: records}}; a defense given one list of records is one run, seed 0."""
    return {d: (dict(recs) if isinstance(recs, dict) else {0: recs}) for d, recs in records_by_defense.items()}


def check_comparable(records_by_defense: dict, reference: str = REFERENCE) -> dict[str, dict[int, RecordSet]]:
    """Validate each defense's records ({defense: records} or {defense: {seed: records}}: one spec, one model per
    run, perturbed items present, the reference's item set); return them as record sets by defense and seed. Raises
    ValueError naming the defense (and seed) at fault."""
    if not records_by_defense:
        raise ValueError("no defenses to compare: records_by_defense is empty")
    if reference not in records_by_defense:
        raise ValueError(f"the reference defense {reference!r} is missing (defenses given: "
                         f"{list(records_by_defense)}); gains are measured against it, so it must be compared too")
    out: dict[str, dict[int, RecordSet]] = {}
    spec: RecordSpec | None = None
    for defense, seeds in as_seeds(records_by_defense).items():
        if not seeds:
            raise ValueError(f"defense {defense!r}: no runs")
        out[defense] = {}
        for seed, recs in seeds.items():
            where = f"defense {defense!r}" + (f" seed {seed}" if len(seeds) > 1 else "")
            try:
                spec = spec or spec_for(list(recs))
                valid = RecordSet(list(recs), spec)
            except (TypeError, ValueError) as err:
                raise ValueError(f"{where}: {err}") from err
            if len(valid.models) != 1:
                raise ValueError(f"{where}: expected the records of one model, got {valid.models or 'none'}")
            if not valid.by_model[valid.models[0]].pert:
                raise ValueError(f"{where}: no perturbed (severity > 0) records; was it scored on a suite?")
            out[defense][seed] = valid
    ref_keys = _item_keys(next(iter(out[reference].values())))
    for defense, seeds in out.items():
        for seed, rs in seeds.items():
            keys = _item_keys(rs)
            if keys != ref_keys:
                where = f"defense {defense!r}" + (f" (seed {seed})" if len(seeds) > 1 else "")
                raise ValueError(f"{where} was scored on different items than {reference!r}: "
                                 f"{len(keys - ref_keys)} item(s) only in {defense!r}, {len(ref_keys - keys)} only "
                                 f"in {reference!r}; compare runs scored on the same suite (cases, illusions, "
                                 f"severities)")
    return out


def _score_row(defense: str, rs: RecordSet) -> dict:
    """One run's row: its model label, clean scores, perturbed scores per category and on average, item count."""
    main = main_table(rs)[0]
    index = rs.by_model[rs.models[0]]
    clean = list(index.clean.values())
    row = {"defense": defense, "model": rs.models[0], "images": len(index.pert)}
    row.update({f"{ORIGINAL}/{s.name}": s.aggregate(clean) for s in rs.scores})
    for cat in [*rs.categories, AVERAGE]:
        for score in rs.scores:
            row[f"{cat}/{score.name}"] = main[f"{cat}/{score.name}/Perturbed"]
    return row


def defense_scores(records_by_defense: dict, reference: str = REFERENCE) -> list[dict]:
    """One row per defense (input order): its model label, clean scores ("original/<score>"), every perturbed
    score per category and on average ("<category>/<score>", "average/<score>"), and the perturbed item count.
    With several seeds per defense ({defense: {seed: records}}) each score is the mean over the seeds, with its
    sample std in "<column>/std" and the number of seeds in "seeds"."""
    valid = check_comparable(records_by_defense, reference)
    several = any(len(seeds) > 1 for seeds in valid.values())
    rows = []
    for defense, seeds in valid.items():
        per_seed = [_score_row(defense, rs) for rs in seeds.values()]
        row = dict(per_seed[0])
        for key in [k for k in row if "/" in k]:
            values = [r[key] for r in per_seed]
            row[key] = sum(values) / len(values)
            if several:
                n = len(values)
                row[f"{key}/std"] = (math.sqrt(sum((v - row[key]) ** 2 for v in values) / (n - 1)) if n > 1
                                     else math.nan)
        if several:
            row["seeds"] = len(per_seed)
        rows.append(row)
    return rows


def _score_names(score_row: dict) -> list[str]:
    """The scores of a defense_scores row, in column order."""
    return list(dict.fromkeys(key.split("/")[1] for key in score_row if key.startswith(f"{ORIGINAL}/")
                              and key.count("/") == 1))


def _groups(score_row: dict) -> list[str]:
    """The column groups of a defense_scores row: categories, then average, then original."""
    groups = list(dict.fromkeys(key.split("/")[0] for key in score_row if "/" in key))
    return [g for g in groups if g != ORIGINAL] + [g for g in groups if g == ORIGINAL]


def defense_gain(score_rows: list[dict], reference: str = REFERENCE, intervals: list[dict] | None = None) -> list[dict]:
    """Long table, one row per (defense other than the reference, category | average | original): the defense's
    score, the reference's, and the gain (defense - reference, points) for every score; with `intervals`
    (report.intervals.gain_rows) also each gain's interval "<score>/low", "<score>/high" and whether it excludes zero,
    "<score>/distinguishable"."""
    bounds = {(r["name"], r["category"]): r for r in intervals or ()}
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
            for metric in _score_names(row):
                key = f"{group}/{metric}"
                out[metric] = row[key]
                out[f"{metric}/{reference}"] = ref.get(key, math.nan)
                out[f"{metric}/gain"] = row[key] - ref.get(key, math.nan)
                interval = bounds.get((row["defense"], group))
                if interval is not None and f"{metric}/low" in interval:
                    out.update({f"{metric}/{k}": interval[f"{metric}/{k}"] for k in ("low", "high", "distinguishable")})
            rows.append(out)
    return rows


def gain_pivot(gain_rows: list[dict], metric: str = "Accuracy", text: bool = False) -> list[dict]:
    """The gain table as one row per defense and one column per category (then average, original): the figure.
    text=True: cells as "gain [low, high] *" where the rows hold intervals (* when it excludes zero)."""
    from lanevil_train.report.intervals import gain_text

    out: dict[str, dict] = {}
    for row in gain_rows:
        value = row[f"{metric}/gain"]
        if text and f"{metric}/low" in row:
            value = gain_text(row, metric)
        out.setdefault(row["defense"], {"defense": row["defense"]})[row["category"]] = value
    return list(out.values())


def headline_of(score_rows: list[dict], spec: RecordSpec):
    """The headline score of a comparison: the first of the spec's scores that the defense rows hold (a VLM's
    judge score when it was judged, else its Language score)."""
    names = {key.split("/")[1] for row in score_rows[:1] for key in row if key.count("/") == 1}
    held = [score for score in spec.scores if score.name in names]
    if not held:
        raise ValueError(f"the defense scores hold none of the {spec.name!r} scores {[s.name for s in spec.scores]}")
    return held[0]


def best_defense(score_rows: list[dict], spec: RecordSpec) -> tuple[str, float]:
    """The defense with the best average perturbed headline score (headline_of; reference included; NaN rows
    ignored)."""
    score = headline_of(score_rows, spec)
    ranked = [(row[f"{AVERAGE}/{score.name}"], row["defense"]) for row in score_rows
              if not math.isnan(row[f"{AVERAGE}/{score.name}"])]
    if not ranked:
        raise ValueError(f"no defense has an average perturbed {score.name}")
    pick = max if score.higher_is_better else min
    value, name = pick(ranked, key=lambda t: t[0])  # keeps the first of equal values: input order
    return name, value


def gain_plot(gain_rows: list[dict], path: str | Path, metrics: str | list[str] = "Accuracy",
              reference: str = REFERENCE) -> Path:
    """Grouped bars, one panel per score of `metrics`: x = category and average, one bar per defense, y = gain over
    the reference in points (the paper's Fig. enhance); where the rows hold intervals, whiskers span them and a bar
    whose interval excludes zero is drawn solid, the others hatched and pale."""
    import matplotlib.pyplot as plt

    from lanevil_train.report.plots import save_figure  # sets the Agg backend

    metrics = [metrics] if isinstance(metrics, str) else list(metrics)
    groups = [g for g in dict.fromkeys(r["category"] for r in gain_rows) if g != ORIGINAL]
    defenses = list(dict.fromkeys(r["defense"] for r in gain_rows))
    n = max(len(defenses), 1)
    width = 0.8 / n
    fig, axes = plt.subplots(len(metrics), 1, figsize=(1.6 + 1.3 * max(len(groups), 1), 3.8 * len(metrics)),
                             squeeze=False)
    for ax, metric in zip(axes[:, 0], metrics):
        by_cell = {(r["defense"], r["category"]): r for r in gain_rows}
        for i, row in enumerate(gain_pivot(gain_rows, metric)):
            xs = [j - 0.4 + width * (i + 0.5) for j in range(len(groups))]
            cells = [by_cell.get((row["defense"], g), {}) for g in groups]
            heights = [row.get(g, math.nan) for g in groups]
            if any(f"{metric}/low" in c for c in cells):
                sure = [bool(c.get(f"{metric}/distinguishable")) for c in cells]
                ax.bar(xs, heights, width, label=row["defense"], color=f"C{i}", edgecolor=f"C{i}")
                for x, h, ok in zip(xs, heights, sure):
                    if not ok:  # repaint as pale and hatched: not told apart from zero
                        ax.bar([x], [h], width, color="white", edgecolor=f"C{i}", hatch="///")
                low = [h - c.get(f"{metric}/low", h) for h, c in zip(heights, cells)]
                high = [c.get(f"{metric}/high", h) - h for h, c in zip(heights, cells)]
                ax.errorbar(xs, heights, yerr=[low, high], fmt="none", ecolor="black", elinewidth=0.8, capsize=2)
            else:
                ax.bar(xs, heights, width, label=row["defense"], color=f"C{i}")
        ax.axhline(0.0, color="black", linewidth=0.8)
        ax.set_xticks(range(len(groups)), [g.replace("_", "\n") for g in groups], fontsize=8)
        ax.set_ylabel(f"{metric} gain over {reference} (points)")
        ax.set_title(f"Perturbed {metric}: gain over "
                     f"{'no defense' if reference == REFERENCE else reference}", fontsize=10)
        ax.grid(axis="y", alpha=0.3)
    if defenses:
        handles, labels = axes[0, 0].get_legend_handles_labels()
        fig.legend(handles, labels, fontsize=8, ncol=min(n, 4), loc="upper center", bbox_to_anchor=(0.5, 0.0))
    fig.tight_layout()
    return save_figure(fig, path)


def write_defense_report(score_rows: list[dict], gain_rows: list[dict], out_dir: str | Path, spec: RecordSpec,
                         runs: dict[str, str] | None = None, interval_note: str | None = None) -> dict[str, Path]:
    """defense_scores.{md,csv,json}, defense_gain.{md,csv,json}, defense_gain.png and compare.md in out_dir.

    `spec` is the records' spec (the headline score it holds picks the best defense; the plot has a panel per
    score, the headline first); `runs` (defense -> run
    directory) is listed in compare.md when given.
    """
    out_dir = Path(out_dir)
    paths: dict[str, Path] = {}
    for name, rows in (("defense_scores", score_rows), ("defense_gain", gain_rows)):
        for fmt, p in write_table(rows, out_dir, name).items():
            paths[f"{name}_{fmt}"] = p
    headline = headline_of(score_rows, spec).name
    names = _score_names(score_rows[0]) if score_rows else []
    paths["plot"] = gain_plot(gain_rows, out_dir / "defense_gain.png", [headline] + [n for n in names
                                                                                    if n != headline])
    best, value = best_defense(score_rows, spec)
    lower = [s.name for s in spec.scores if not s.higher_is_better and s.name in names]
    unit = spec.unit
    parts = ["# Defense comparison", "",
             f"Scores in {unit}, gains in points (defense minus none) on the same illusion suite. Per "
             "category: all perturbed items of the category; average: mean of the categories; original: the "
             "suite's clean items (a negative original gain is a cost in clean performance)."
             + (f" Lower is better for {', '.join(lower)}: there a negative gain is an improvement." if lower else ""),
             "", f"Best average perturbed {headline}: **{best}** ({value:.2f}{unit}).", ""]
    if interval_note:
        parts += [interval_note, ""]
    for name in names:
        parts += [f"## {name} gain over none (points)", "", markdown_table(gain_pivot(gain_rows, name, text=True)), ""]
    shown = [{k: v for k, v in row.items() if not k.endswith("/std")} for row in score_rows]
    if any("seeds" in row for row in score_rows):
        from lanevil_train.report.intervals import mean_std_text

        shown = [{k: (mean_std_text(row, k) if f"{k}/std" in row else v) for k, v in row.items()
                  if not k.endswith("/std")} for row in score_rows]
    parts += [f"![defense gain]({paths['plot'].name})", "",
              "## Scores per defense (perturbed per category and average; original = clean)", "",
              markdown_table(shown), "",
              "Long form with each side of every gain: defense_gain.md / .csv / .json.", ""]
    if runs:
        listed = [{"defense": d, "seed": seed, "run": str(r)} for d, by_seed in runs.items()
                  for seed, r in (by_seed.items() if isinstance(by_seed, dict) else [(None, by_seed)])]
        if all(row["seed"] is None for row in listed):
            listed = [{"defense": row["defense"], "run": row["run"]} for row in listed]
        parts += ["## Runs", "", markdown_table(listed), ""]
    paths["report"] = out_dir / "compare.md"
    atomic_write_text(paths["report"], "\n".join(parts))
    return paths
