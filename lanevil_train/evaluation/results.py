"""Write what an evaluation found: headline scores, and the robustness report when there are illusions."""

from __future__ import annotations

import re
from pathlib import Path

import pytorch_lightning as pl

from lanevil_train.evaluation.lane_records import PerImageWriter, read_records
from lanevil_train.report.specs import record_set
from lanevil_train.report.summary import summary_rows
from lanevil_train.report.tables import print_table, write_table


def write_results(result_files: list[Path], out_dir: Path, baseline: str | None = None,
                  labels: dict[Path, str] | None = None, html: bool = True) -> float:
    """Tables (and plots) from per-image results files; returns the headline score (Accuracy % for lanes) of the
    perturbed images (of all images if none is perturbed): the value a sweep optimises.

    Records are read without their stored lanes, then read again keeping lanes only for the few
    worst cases that get drawn, so memory stays small however many images were scored. `labels`: a model label
    for the records of some files (a seed run's "<label> (seed s)"), replacing their own. `html`: also write
    report.html beside report.md (report/page/; task.html), when there is a robustness report.
    """
    labels = labels or {}

    def read(path: Path, **kwargs) -> list[dict]:
        records = read_records(path, keep_lanes=False, **kwargs)
        return [{**r, "model": labels[path]} for r in records] if path in labels else records

    records = [r for path in result_files for r in read(path)]
    if not records:
        raise ValueError(f"no per-image results to report in {', '.join(map(str, result_files))}")
    rs = _checked_record_set(records, result_files)
    if any(r["severity"] > 0 for r in rs.records):
        from lanevil_train.report.plots import worst_case_pairs

        drawn = {r["key"] for pair in worst_case_pairs(rs) for r in pair}
        if drawn:
            records = [r for path in result_files for r in read(path, lanes_for=drawn)]
            rs = record_set(records, rs.spec)
    rows = summary_rows(rs.records, rs.spec)
    write_table(rows, out_dir, "test_scores")
    print_table(rows, title=f"Scores ({rs.spec.unit}) — {out_dir}")
    perturbed = [r for r in rs.records if r["severity"] > 0]
    if perturbed:
        from lanevil_train.report.robustness import main_long, main_table, write_report

        paths = write_report(rs, out_dir, baseline=baseline)
        print_table(main_long(main_table(rs)),
                    title=f"Robustness ({rs.spec.unit}): Perturbed / Original / Gap — full table in main.md")
        plots = ", ".join(p.name for p in paths.values() if p.suffix == ".png")
        print(f"Robustness report: {paths['report']} (per type, per severity, relative); plots: {plots}")
        if html:
            from lanevil_train.report.page import write_robustness_page

            print(f"Report page: {write_robustness_page(out_dir, result_files, rs, labels)}")
    return rs.headline.aggregate(perturbed or rs.records)


def _checked_record_set(records: list[dict], result_files: list[Path]):
    """record_set(records); a bad record is reported with the file and line it came from."""
    try:
        return record_set(records)
    except ValueError as error:
        for path in result_files:  # find the file: each file's records are validated on their own
            part = read_records(path, keep_lanes=False)
            try:
                record_set(part)
            except ValueError as file_error:
                line = re.match(r"^record (\d+): ", str(file_error))  # record i is line i + 1 of its file
                where = f"{path}:{int(line.group(1)) + 1}" if line else str(path)
                raise ValueError(f"{where}: {str(file_error)[line.end() if line else 0:]}") from None
        raise error  # records of several files that do not fit together


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
                logger.log_table(key=f"evaluate/{name}", columns=columns,
                                 data=[[r.get(c) for c in columns] for r in rows])
        pngs = sorted(Path(out_dir).glob("*.png"))
        if pngs:
            logger.log_image(key="evaluate/plots", images=[str(p) for p in pngs], caption=[p.stem for p in pngs])
    else:
        for row in tables.get("test_scores", []):
            kind = next(value for key, value in row.items() if key.endswith("_kind"))  # images_kind, answers_kind
            prefix = f"{row['dataset']}/{kind}"
            logger.log_metrics({f"{prefix}/{k}": v for k, v in row.items() if isinstance(v, (int, float))})
    logger.save()
    if hasattr(logger, "experiment") and hasattr(logger.experiment, "finish"):
        logger.experiment.finish()


def score_test_set(trainer: pl.Trainer, model: pl.LightningModule, datamodule: pl.LightningDataModule,
                   writer: PerImageWriter, ckpt_path: str | None = None) -> float | None:
    """Run trainer.test (the trainer must carry `writer`); rank 0 writes the score tables beside the per-image
    results and returns the Accuracy (%); other ranks return None."""
    if writer not in trainer.callbacks:
        raise ValueError("score_test_set: the trainer was built without the PerImageWriter callback it was given")
    trainer.test(model, datamodule=datamodule, ckpt_path=ckpt_path, verbose=False)
    if not trainer.is_global_zero:
        return None
    return write_results([writer.path], writer.path.parent)
