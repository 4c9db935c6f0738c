"""Score a detector on a datamodule's test split and write the results table (JSON, CSV, markdown)."""

from __future__ import annotations

from pathlib import Path

import pytorch_lightning as pl

from lanevil_train.data.datamodule import LaneDataModule
from lanevil_train.models.detector import LaneDetector
from lanevil_train.report.tables import print_table, write_table

SCORE_KEYS = ("Accuracy", "FP", "FN", "F1")


def score_test_set(trainer: pl.Trainer, model: LaneDetector, datamodule: LaneDataModule, out_dir: Path,
                   label: dict, ckpt_path: str | None = None) -> dict:
    """Run trainer.test, print and save the TuSimple scores (in %), and the per-image scores."""
    trainer.test(model, datamodule=datamodule, ckpt_path=ckpt_path, verbose=False)
    metrics = trainer.callback_metrics
    row = dict(label)
    for key in SCORE_KEYS:
        row[key] = 100.0 * float(metrics[f"test/{key}"])
    row["images"] = len(datamodule.sets["test"])
    if trainer.is_global_zero:
        write_table([row], out_dir, "test_scores")
        print_table([row], title=f"Clean test scores (%) — {out_dir}")
    per_image = sorted(model.test_records, key=lambda r: r["case_id"])
    name = "per_image" if trainer.world_size == 1 else f"per_image_rank{trainer.global_rank}"
    if per_image:
        write_table(per_image, out_dir, name, digits=4)
    return row
