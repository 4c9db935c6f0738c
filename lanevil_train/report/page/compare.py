"""report.html of task=compare: gains over `none` with their intervals, scores per defense, links to each run's
page.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from lanevil_train.report.page.header import add_run_header, run_identities
from lanevil_train.report.page.html import GAP_LEGEND, PAGE, Cell, Page, esc, slug, table_html
from lanevil_train.report.page.tables import _lower, add_plots


# ------------------------------------------------------------------------------------------- compare page
def write_compare_page(out_dir: str | Path, score_rows: Sequence[dict], gain_rows: Sequence[dict], spec,
                       runs: dict | None = None, note: str | None = None, result_files: Sequence[Path] = ()) -> Path:
    """report.html beside compare.md (task=compare), from the rows compare.md is made of (defense_scores,
    defense_gain with their bootstrap intervals): the best defense, a gain table per score (a row per defense, a
    column per category, each gain with its interval), the scores per defense (mean ± std over seeds), the gain
    plot and the runs, each linked to its own report.html where it has one. `result_files`: the runs' results
    files, for the header's model lines (weights hashes)."""
    from lanevil_train.report.defenses import REFERENCE, _score_names, best_defense, gain_pivot, headline_of

    out_dir = Path(out_dir)
    page = Page("Defense comparison")
    add_run_header(page, out_dir, run_identities(list(result_files)),
                   list(dict.fromkeys(str(r.get("model")) for r in score_rows)))
    lower = _lower(spec)
    headline = headline_of(list(score_rows), spec).name
    best, value = best_defense(list(score_rows), spec)
    intro = (f"<p>Best average perturbed {esc(headline)}: <b>{esc(best)}</b> ({value:.2f}{esc(spec.unit)}). Gains "
             f"in points: defense minus {esc(REFERENCE)}, on the same suite; original = the suite's clean items.</p>")
    if note:
        intro += f'<p class="note">{esc(note)}</p>'
    page.add_section("Summary", intro, "summary")
    names = _score_names(score_rows[0]) if score_rows else []
    by_cell = {(r["defense"], r["category"]): r for r in gain_rows}
    parts = []
    for name in names:
        table = []
        for row in gain_pivot(list(gain_rows), name):
            cells = {"defense": row["defense"]}
            for group, gain in row.items():
                if group == "defense":
                    continue
                full = by_cell.get((row["defense"], group), {})
                low, high = full.get(f"{name}/low"), full.get(f"{name}/high")
                cells[group] = Cell(gain, low, high, mark="*" if full.get(f"{name}/distinguishable") else "")
            table.append(cells)
        parts.append(table_html(table, f"table-gain-{slug(name)}", caption=f"{name} gain over {REFERENCE} (points)"
                                + (" [interval]; * excludes zero" if any(f"{name}/low" in r for r in gain_rows)
                                   else ""),
                                lower_is_better=[name] if name in lower else [],
                                gap_columns=lambda c: c.key != "defense"))
    page.add_section("Gains over " + REFERENCE, GAP_LEGEND.replace("Gap = Perturbed - Original; coloured",
                                                                  "Gain coloured") + "".join(parts), "gains")
    shown = []
    for row in score_rows:
        cells = {}
        for key, v in row.items():
            if key.endswith("/std"):
                continue
            std = row.get(f"{key}/std")
            cells[key] = Cell(v, std=std, key=key) if std is not None else Cell(v, key=key)
        shown.append(cells)
    page.add_section("Scores per defense", table_html(shown, "table-defense_scores", lower_is_better=lower,
                                                      caption="Perturbed per category and average; original = "
                                                              "clean"), "scores")
    add_plots(page, out_dir, ["defense_gain.png"])
    if runs:
        listed = []
        for defense, by_seed in runs.items():
            for seed, run in (by_seed.items() if isinstance(by_seed, dict) else [(None, by_seed)]):
                pages = [p for p in (Path(run) / "robustness" / PAGE, Path(run) / "test" / PAGE) if p.is_file()]
                href = _relative(pages[0], out_dir) if pages else None
                listed.append({"defense": defense, **({"seed": seed} if seed is not None else {}),
                               "run": Cell(str(run), href=href)})
        page.add_section("Runs", '<p class="note">Each run links to its own page where it wrote one.</p>'
                         + table_html(listed, "table-runs"), "runs")
    return page.write(out_dir)


def _relative(target: Path, base: Path) -> str:
    """target's path relative to the folder base, with / separators (a link on the page)."""
    import os

    return Path(os.path.relpath(Path(target).resolve(), Path(base).resolve())).as_posix()
