"""The combined-illusion table (paper §5.6, Table combined): for each pair of illusion categories, the model's score
on the pair's images (Perturbed), on the same cases' clean images (Original) and their Gap, and the Gap against each
of the pair's single illusions alone on the same cases and severities -- does the second illusion add to the first?

Records: a combined suite's (perturbations.py: illusion "<a>+<b>", category "<category a>+<category b>"), each case
holding the clean image, each single illusion and their pairs at the same severities.
"""

from __future__ import annotations

from lanevil_train.report.records import NAN, RecordSet
from lanevil_train.report.tables import markdown_table
from lanevil_train.taxonomy import PAIR, pair_label

ROWS = ("Original", "Perturbed", "Gap", "first alone", "second alone", "Gap vs first", "Gap vs second")


def pair_categories(rs: RecordSet) -> list[str]:
    """The records' pair categories ("<a>+<b>"), in the order the report lists categories."""
    return [c for c in rs.categories if PAIR in c]


def combined_table(rs: RecordSet) -> list[dict]:
    """One row per (model, pair category): each score's Original, Perturbed, Gap, the single illusions' scores on the
    same (case, severity) items and the pair's Gap against each ("<score>/<row>" columns, rows as in ROWS)."""
    rows = []
    for model in rs.models:
        index = rs.by_model[model]
        singles = {(r["dataset"], r["case_id"], r["illusion"], r["severity"]): r for r in index.pert
                   if PAIR not in r["illusion"]}
        for category in pair_categories(rs):
            pert = [r for r in index.pert if r["category"] == category]
            values = index.pog(pert, rs.scores)
            firsts, seconds = [], []
            for r in pert:
                first, second = r["illusion"].split(PAIR)
                firsts.append(singles.get((r["dataset"], r["case_id"], first, r["severity"])))
                seconds.append(singles.get((r["dataset"], r["case_id"], second, r["severity"])))
            row = {"model": model, "pair": pair_label(category), "category": category,
                   rs.spec.count_name: len(pert)}
            for score in rs.scores:
                p = values[f"{score.name}/Perturbed"]
                alone = [score.aggregate(found) if found and all(x is not None for x in found) else NAN
                         for found in (firsts, seconds)]
                row.update({f"{score.name}/Original": values[f"{score.name}/Original"], f"{score.name}/Perturbed": p,
                            f"{score.name}/Gap": values[f"{score.name}/Gap"],
                            f"{score.name}/first alone": alone[0], f"{score.name}/second alone": alone[1],
                            f"{score.name}/Gap vs first": p - alone[0], f"{score.name}/Gap vs second": p - alone[1]})
            rows.append(row)
    return rows


def combined_markdown(rows: list[dict], score: str) -> str:
    """The paper's layout for one score and model at a time: rows Original / Perturbed / Gap / ..., a column per
    pair (RD+TO, RD+SH, ...)."""
    parts = []
    for model in dict.fromkeys(r["model"] for r in rows):
        mine = [r for r in rows if r["model"] == model]
        table = [{"model": model, "metric": name, **{r["pair"]: r[f"{score}/{name}"] for r in mine}} for name in ROWS]
        parts.append(markdown_table(table))
    return "\n\n".join(parts)
