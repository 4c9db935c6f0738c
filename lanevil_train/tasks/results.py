"""Write what an evaluation found: headline scores, and the robustness report when there are illusions."""

from __future__ import annotations

from pathlib import Path

from lanevil_train.report.scores import summarise, summary_rows
from lanevil_train.report.tables import print_table, write_table
from lanevil_train.tasks.streaming import read_records


def write_results(result_files: list[Path], out_dir: Path, baseline: str | None = None) -> dict:
    """Tables (and plots) from per-image results files; returns the scores of the perturbed images (all if none).

    Records are read without their stored lanes, then read again keeping lanes only for the few
    worst cases that get drawn, so memory stays small however many images were scored.
    """
    records = [r for path in result_files for r in read_records(path, keep_lanes=False)]
    if not records:
        raise ValueError(f"no per-image results to report in {out_dir}")
    if any(r.get("severity", 0) > 0 for r in records):
        from lanevil_train.report.plots import worst_case_pairs

        drawn = {r["key"] for pair in worst_case_pairs(records) for r in pair}
        if drawn:
            records = [r for path in result_files for r in read_records(path, keep_lanes=False, lanes_for=drawn)]
    rows = summary_rows(records)
    write_table(rows, out_dir, "test_scores")
    print_table(rows, title=f"Scores (%) — {out_dir}")
    perturbed = [r for r in records if r.get("severity", 0) > 0]
    if perturbed:
        from lanevil_train.report.robustness import main_table, write_report

        write_report(records, out_dir, baseline=baseline)
        print_table(_long(main_table(records)), title="Robustness (%): Perturbed / Original / Gap — full table in main.md")
    return summarise(perturbed or records)


def _long(main_rows: list[dict]) -> list[dict]:
    """The paper-layout table (one wide row per model) as one row per (model, category), for a console."""
    out = []
    for row in main_rows:
        categories = dict.fromkeys(key.split("/")[0] for key in row if key.count("/") == 2)
        for category in categories:
            out.append({"model": row["model"], "category": category,
                        **{f"{metric} {kind}": row[f"{category}/{metric}/{kind}"]
                           for metric in ("Accuracy", "F1") for kind in ("Perturbed", "Original", "Gap")}})
    return out


def log_results(logger, out_dir: Path) -> None:
    """Send the written tables and plots to a Lightning logger: wandb gets tables and images,
    any other logger the headline scores as metrics."""
    if not logger:
        return
    import json

    tables = {path.stem: json.loads(path.read_text()) for path in sorted(Path(out_dir).glob("*.json"))
              if path.stem not in ("per_image",)}
    if hasattr(logger, "log_table"):  # WandbLogger
        for name, rows in tables.items():
            if rows and isinstance(rows, list) and isinstance(rows[0], dict):
                columns = list(rows[0])
                logger.log_table(key=f"evaluate/{name}", columns=columns, data=[[r.get(c) for c in columns] for r in rows])
        pngs = sorted(Path(out_dir).glob("*.png"))
        if pngs:
            logger.log_image(key="evaluate/plots", images=[str(p) for p in pngs], caption=[p.stem for p in pngs])
    else:
        for row in tables.get("test_scores", []):
            prefix = f"{row['dataset']}/{row['images_kind']}"
            logger.log_metrics({f"{prefix}/{k}": v for k, v in row.items() if isinstance(v, (int, float))})
    logger.save()
    if hasattr(logger, "experiment") and hasattr(logger.experiment, "finish"):
        logger.experiment.finish()
