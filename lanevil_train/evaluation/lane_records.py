"""One per-image scoring path for lane detectors: the record every evaluation writes (training's clean test,
task=evaluate, the robustness suites), and the Lightning callback that writes training's test records.

A record (report/specs.py LANE_SPEC): {model, dataset, spec, key, case_id, image, illusion, category, severity,
accuracy, fp, fn (TuSimple per image), tp_count, fp_count, fn_count (TuSimple lane counts, for F1_count),
culane_tp, culane_fp, culane_fn, culane_tp_sweep (TP at the mF1 thresholds; not for LLAMAS or CurveLanes),
num_pred, num_gt, pred_lanes, gt_lanes (integer [x, y] at the scoring rows)};
it streams to per_image.jsonl, which task=report reads.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytorch_lightning as pl

from lanevil_train.lanes import culane_lanes, lanes_to_rows
from lanevil_train.metrics import (
    culane_image_counts_multi,
    curvelanes_image_counts,
    llamas_image_counts,
    tusimple_lane_scores,
)
from lanevil_train.report.specs import CULANE_SWEEP, LANE_SPEC
from lanevil_train.results_log import ResultsLog

LANE_FIELDS = ("pred_lanes", "gt_lanes")
RESULTS = "per_image.jsonl"


def _compact(lanes: list[np.ndarray], rows: np.ndarray, row_sampling: str = "linear",
             height: float | None = None) -> list[list[list[int]]]:
    """Lanes sampled at the scoring rows (as `row_sampling` reads them), as integer [x, y] lists (small enough to
    keep per image)."""
    out = []
    for xs in lanes_to_rows(lanes, rows, row_sampling, height):
        valid = xs >= 0
        out.append(np.stack([np.round(xs[valid]), rows[valid]], 1).astype(int).tolist())
    return out


def lane_record(pred: list[np.ndarray], gt: list[np.ndarray], meta: dict, keep_lanes: bool = True,
                row_sampling: str = "linear", culane_rows=None) -> dict:
    """The per-image record of predicted vs ground-truth lanes (original-image pixels) of the sample `meta`
    describes: TuSimple accuracy/FP/FN and lane counts (F1_count's TP/FP/FN) at its h_samples (the predicted lanes
    read there as `row_sampling` says, the model's) and CULane TP/FP/FN (30 px lanes at 1640 px wide; a LLAMAS
    image, meta "culane_metric" "llamas", by the official LLAMAS procedure: metrics/llamas.py; a CurveLanes one,
    "curvelanes", by its procedure: metrics/curvelanes.py), of the predicted
    lanes as the CULane file has them (lanes.culane_lanes: at `culane_rows` when given)."""
    width, height = int(meta["width"]), int(meta["height"])
    sweep = None
    acc, fp, fn, tp_count, fp_count, fn_count = tusimple_lane_scores(pred, gt, meta["h_samples"], with_counts=True,
                                                                     row_sampling=row_sampling, height=height)
    if meta.get("culane_metric") == "llamas":
        if (width, height) != (1276, 717):
            raise ValueError(f"{meta.get('source') or meta['case_id']}: a LLAMAS image is 1276x717 (the official "
                             f"metric's canvas), got {width}x{height}")
        tp, cfp, cfn = llamas_image_counts(pred, gt)  # its own 30 px on its 1276x717 images, rows >= 300
    elif meta.get("culane_metric") == "curvelanes":  # 5 px lanes, every image scaled to 224x224
        written = culane_lanes(pred, culane_rows, row_sampling, height, width)
        tp, cfp, cfn = curvelanes_image_counts(written, gt, (height, width))
    else:
        lane_width = max(1, round(30 * width / 1640))  # CULane draws 30 px lanes on 1640 px wide images
        written = culane_lanes(pred, culane_rows, row_sampling, height, width)
        counts = culane_image_counts_multi(written, gt, width=width, height=height, lane_width=lane_width)
        tp, cfp, cfn = counts[0]  # IoU 0.5, the first mF1 threshold
        sweep = [c[0] for c in counts]  # TP at 0.50, 0.55, ..., 0.95: F1@75 and mF1 (report/specs.py)
    record = {"spec": LANE_SPEC.name, "key": meta.get("key", meta["case_id"]), "case_id": meta["case_id"],
              "image": meta.get("image_path"), "illusion": meta.get("illusion"), "category": meta.get("category"),
              "severity": int(meta.get("severity") or 0), "accuracy": acc, "fp": fp, "fn": fn,
              "tp_count": tp_count, "fp_count": fp_count, "fn_count": fn_count,
              "culane_tp": int(tp), "culane_fp": int(cfp), "culane_fn": int(cfn),
              "num_pred": len(pred), "num_gt": len(gt)}
    if sweep is not None:
        record[CULANE_SWEEP] = sweep
    if keep_lanes:
        rows = np.asarray(meta["h_samples"], dtype=np.float64)
        record.update(pred_lanes=_compact(pred, rows, row_sampling, height), gt_lanes=_compact(gt, rows))
    return record


def read_records(path: str | Path, keep_lanes: bool = True, lanes_for: set[str] | None = None) -> list[dict]:
    """All complete records of a per-image results file; keep_lanes=False drops the stored lanes (most of a
    record's size) except for the keys in `lanes_for`."""
    return ResultsLog(path).records(drop=() if keep_lanes else LANE_FIELDS, keep_for=lanes_for)


class PerImageWriter(pl.Callback):
    """Writes every test image's record to `path` (per_image.jsonl) during trainer.test.

    Each rank appends to its own part file; at the end of the test epoch rank 0 merges the parts into `path`
    (images a DistributedSampler gave twice, to even out the ranks, counted once; sorted by key) and removes
    them. A test killed part-way leaves only part files, which the next test run overwrites.
    """

    def __init__(self, path: str | Path, label: dict):
        self.path = Path(path)
        self.label = dict(label)

    def _part(self, rank: int) -> Path:
        return self.path.with_name(f"{self.path.stem}.rank{rank}{self.path.suffix}")

    def on_test_epoch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        part = self._part(trainer.global_rank)
        part.parent.mkdir(parents=True, exist_ok=True)
        part.unlink(missing_ok=True)

    def on_test_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs, batch, batch_idx: int,
                          dataloader_idx: int = 0) -> None:
        reading = {"row_sampling": getattr(pl_module, "row_sampling", "linear"),
                   "culane_rows": getattr(pl_module, "culane_rows", None)}
        records = [{**self.label, **lane_record(pred, gt, meta, **reading)}
                   for pred, gt, meta in zip(outputs, batch["lanes"], batch["meta"])]
        ResultsLog(self._part(trainer.global_rank)).append(records)

    def on_test_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        trainer.strategy.barrier("per_image_parts_written")
        if not trainer.is_global_zero:
            return
        merged: dict[str, dict] = {}
        parts = [self._part(rank) for rank in range(trainer.world_size)]
        for part in parts:
            if part.exists():
                for record in ResultsLog(part).records():
                    merged.setdefault(record["key"], record)
        tmp = self.path.with_name(self.path.name + ".tmp")
        tmp.unlink(missing_ok=True)
        ResultsLog(tmp).append(merged[key] for key in sorted(merged))
        os.replace(tmp, self.path)
        for part in parts:
            part.unlink(missing_ok=True)

