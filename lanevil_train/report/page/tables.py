"""The tables of report.md on the page, from the same rows (main.json, per_type.json, ... as report/robustness.py
wrote them), the seeds' tables (seeds.json, seed_gains.json as task=report wrote them) and the run's PNG plots (score
vs severity, the type x severity heatmap, gain bars), each as a section.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Iterable, Sequence

from lanevil_train.report.page.html import GAP_LEGEND, Cell, Page, perturbed_named, plots_html, slug, table_html


# ---------------------------------------------------------------------------------------------- lane tables
def _load_rows(out_dir: Path, name: str) -> list[dict] | None:
    path = out_dir / f"{name}.json"
    if not path.is_file():
        return None
    rows = json.loads(path.read_text(encoding="utf-8"))
    return rows if isinstance(rows, list) else None


def main_long_cells(main_rows: Sequence[dict]) -> list[dict]:
    """main.json's wide rows (one per model) as one row per (model, category) with "<score>/<kind>" cells, each a
    Cell naming its main.json column (data-key)."""
    out = []
    for row in main_rows:
        by_group: dict[str, dict] = {}
        for key, value in row.items():
            if key.count("/") == 2:
                group, score, kind = key.split("/")
                by_group.setdefault(group, {})[f"{score}/{kind}"] = Cell(value, key=key)
        out += [{"model": row["model"], "category": group, **cells} for group, cells in by_group.items()]
    return out


# the tables of report.md, in its order: (JSON stem, title); per_<field> tables are found by their files
TABLES = (("main", "Robustness per category"), ("per_type", "Per illusion type"),
          ("per_severity", "Per severity level"))
LATER_TABLES = (("relative", "Relative robustness"),)


def _lower(spec) -> list[str]:
    return [s.name for s in spec.scores if not s.higher_is_better] if spec is not None else []


def add_robustness_tables(page: Page, out_dir: Path, spec=None) -> None:
    """The tables write_report wrote (main, per type, per severity, per group field, relative, combined) as
    sections, from their JSON files."""
    lower = _lower(spec)
    scores = [s.name for s in spec.scores] if spec is not None else []
    summary = _load_rows(out_dir, "test_scores")
    if summary:
        page.add_section("Scores", table_html(summary, "table-test_scores",
                                              caption="Headline scores per model, dataset and kind of image"),
                         "scores")
    names = [*TABLES, *[(p.stem, "Per " + p.stem[4:].replace("_", " ")) for p in sorted(out_dir.glob("per_*.json"))
                        if p.stem not in dict(TABLES) and "." not in p.stem], *LATER_TABLES,
             ("combined", "Combined illusions")]
    unit = spec.unit if spec is not None else "%"
    for name, title in names:
        rows = _load_rows(out_dir, name)
        if rows is None:
            continue
        if name == "main":
            body = GAP_LEGEND + table_html(main_long_cells(rows), "table-main", lower_is_better=lower,
                                           caption=f"Perturbed / Original / Gap per category ({unit}); average = "
                                                   f"mean of the categories")
        else:
            body = table_html(perturbed_named(rows, scores), f"table-{name}", lower_is_better=lower)
        page.add_section(title, body, name)


def add_plots(page: Page, out_dir: Path, names: Iterable[str], title: str = "Plots") -> None:
    body = plots_html(out_dir, names)
    if body:
        page.add_section(title, body, "plots")


def robustness_plots(out_dir: Path) -> list[str]:
    """The PNGs write_report draws that the page shows (score vs severity, the gap heatmap), seeds' gain bars."""
    return ([p.name for p in sorted(out_dir.glob("*_vs_severity.png"))] + ["gap_heatmap.png"]
            + [p.name for p in sorted(out_dir.glob("seed_gains*.png"))])


# --------------------------------------------------------------------------------------------------- seeds
def add_seed_tables(page: Page, out_dir: Path, spec=None) -> None:
    """seeds.json (mean ± std over seeds) and seed_gains.json (gains with their intervals) as pivot tables: a row
    per model, a column per category."""
    scores_rows, gains = _load_rows(out_dir, "seeds"), _load_rows(out_dir, "seed_gains") or []
    if not scores_rows:
        return
    lower = _lower(spec)
    parts = []
    for dataset in dict.fromkeys(r["dataset"] for r in scores_rows):
        mine = [r for r in scores_rows if r["dataset"] == dataset]
        names = [k for k in mine[0] if f"{k}/std" in mine[0]]
        for score in names:
            table = [{"model": name, **{r["category"]: Cell(r[score], std=r[f"{score}/std"]) for r in mine
                                        if r["name"] == name}} for name in dict.fromkeys(r["name"] for r in mine)]
            parts.append(table_html(table, f"table-seeds-{slug(dataset)}-{slug(score)}",
                                    caption=f"{dataset}: {score}, mean ± std over seeds"))
        mine_gains = [r for r in gains if r["dataset"] == dataset]
        for score in names:
            if not mine_gains or f"{score}/gain" not in mine_gains[0]:
                continue
            table = [{"model": name, **{r["category"]: Cell(r[f"{score}/gain"], r[f"{score}/low"], r[f"{score}/high"],
                                                           mark="*" if r[f"{score}/distinguishable"] else "")
                                        for r in mine_gains if r["name"] == name}}
                     for name in dict.fromkeys(r["name"] for r in mine_gains)]
            parts.append(table_html(table, f"table-seed_gains-{slug(dataset)}-{slug(score)}",
                                    caption=f"{dataset}: {score} gain over the reference (points), interval; * "
                                            f"excludes zero", lower_is_better=lower,
                                    gap_columns=lambda c: c.key != "model"))
    page.add_section("Seeds", "".join(parts), "seeds")
