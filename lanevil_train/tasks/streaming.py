"""Batched, streaming, resumable evaluation: one JSON line of scores per image, appended as produced.

Memory stays flat whatever the test-set size (nothing is accumulated but the output file), and a
rerun with the same output file skips every image it already lists.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch.utils.data import DataLoader, Dataset, Subset

from lanevil_train.data.datamodule import ProcessedDataset, collate_lanes
from lanevil_train.data.transforms import LaneSampleProcessor
from lanevil_train.models.detector import LaneDetector
from lanevil_train.progress import progress_counter
from lanevil_train.results_log import ResultsLog
from lanevil_train.tasks.scoring import lane_record


def stream_evaluate(model: LaneDetector, dataset: Dataset, out_path: str | Path, label: dict,
                    batch_size: int = 8, num_workers: int = 0, progress: str = "auto",
                    keep_lanes: bool = True) -> Path:
    """Score every image of `dataset` not yet in `out_path`, appending one JSON line each.

    `label` (e.g. {"model": ..., "dataset": ...}) is copied into every line; `progress` is a
    lanevil_train.progress mode (auto, rich, tqdm, plain, none).
    """
    log = ResultsLog(out_path)
    done = log.resume()
    todo = [i for i in range(len(dataset)) if dataset.item_key(i) not in done]
    spec = model.build_config or {}
    processor = LaneSampleProcessor(tuple(spec.get("input_size", dataset[0]["image"].shape[:2])), augment=False,
                                    crop_top=spec.get("crop_top", 0.0))
    loader = DataLoader(ProcessedDataset(Subset(dataset, todo), processor), batch_size=batch_size,
                        shuffle=False, num_workers=num_workers, collate_fn=collate_lanes)
    bar = progress_counter(len(dataset), len(dataset) - len(todo), "evaluate", "img", progress)
    model.eval()
    device = next(model.parameters()).device
    with torch.inference_mode():
        for batch in loader:
            sizes = [(int(m["height"]), int(m["width"])) for m in batch["meta"]]
            preds = model.predict_lanes(batch["images"].to(device), sizes)
            log.append({**label, **lane_record(pred, gt, meta, keep_lanes)}
                       for pred, gt, meta in zip(preds, batch["lanes"], batch["meta"]))
            bar.update(len(preds))
    bar.close()
    return log.path
