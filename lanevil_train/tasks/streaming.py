"""Batched, streaming, resumable evaluation: one JSON line of scores per image, appended as produced.

Memory stays flat whatever the test-set size (nothing is accumulated but the output file), and a
rerun with the same output file skips every image it already lists.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Subset

from lanevil_train.data.datamodule import ProcessedDataset, collate_lanes
from lanevil_train.data.transforms import LaneSampleProcessor
from lanevil_train.lanes import lanes_to_rows
from lanevil_train.metrics.tusimple import tusimple_lane_scores
from lanevil_train.models.detector import LaneDetector


def item_key(dataset: Dataset, index: int) -> str:
    """The dataset's stable name for an item (datasets here all define item_key)."""
    return dataset.item_key(index)


def finished_keys(path: Path) -> set[str]:
    """Keys of the images a per-image results file already holds (a torn last line is ignored)."""
    if not path.exists():
        return set()
    keys = set()
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            keys.add(json.loads(line)["key"])
        except (json.JSONDecodeError, KeyError, TypeError):
            continue
    return keys


def _compact(lanes: list[np.ndarray], rows: np.ndarray) -> list[list[list[int]]]:
    """Lanes sampled at the scoring rows, as integer [x, y] lists (small enough to keep per image)."""
    out = []
    for xs in lanes_to_rows(lanes, rows):
        valid = xs >= 0
        out.append(np.stack([np.round(xs[valid]), rows[valid]], 1).astype(int).tolist())
    return out


def score_image(pred: list[np.ndarray], gt: list[np.ndarray], meta: dict) -> dict:
    """TuSimple per-image scores (and CULane TP/FP/FN where metrics.culane is available)."""
    acc, fp, fn = tusimple_lane_scores(pred, gt, meta["h_samples"])
    scores = {"accuracy": acc, "fp": fp, "fn": fn, "num_pred": len(pred), "num_gt": len(gt)}
    try:
        from lanevil_train.metrics.culane import culane_image_counts
    except ImportError:
        return scores
    width, height = int(meta["width"]), int(meta["height"])
    lane_width = max(1, round(30 * width / 1640))  # CULane draws 30 px lanes on 1640 px wide images
    tp, cfp, cfn = culane_image_counts(pred, gt, width=width, height=height, lane_width=lane_width)
    scores.update(culane_tp=int(tp), culane_fp=int(cfp), culane_fn=int(cfn))
    return scores


def stream_evaluate(model: LaneDetector, dataset: Dataset, out_path: str | Path, label: dict,
                    batch_size: int = 8, num_workers: int = 0, progress: bool = True,
                    keep_lanes: bool = True) -> Path:
    """Score every image of `dataset` not yet in `out_path`, appending one JSON line each.

    `label` (e.g. {"model": ..., "dataset": ...}) is copied into every line.
    """
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    _drop_torn_tail(out_path)
    done = finished_keys(out_path)
    todo = [i for i in range(len(dataset)) if item_key(dataset, i) not in done]
    spec = model.build_config or {}
    processor = LaneSampleProcessor(tuple(spec.get("input_size", dataset[0]["image"].shape[:2])), augment=False,
                                    crop_top=spec.get("crop_top", 0.0))
    loader = DataLoader(ProcessedDataset(Subset(dataset, todo), processor), batch_size=batch_size,
                        shuffle=False, num_workers=num_workers, collate_fn=collate_lanes)
    bar = _progress(len(dataset), len(dataset) - len(todo), progress)
    model.eval()
    device = next(model.parameters()).device
    with open(out_path, "a", encoding="utf-8") as handle, torch.inference_mode():
        for batch in loader:
            sizes = [(int(m["height"]), int(m["width"])) for m in batch["meta"]]
            preds = model.predict_lanes(batch["images"].to(device), sizes)
            for pred, gt, meta in zip(preds, batch["lanes"], batch["meta"]):
                record = {**label, "key": meta.get("key", meta["case_id"]), "case_id": meta["case_id"],
                          "image": meta.get("image_path"), "illusion": meta.get("illusion"),
                          "category": meta.get("category"), "severity": int(meta.get("severity", 0)),
                          **score_image(pred, gt, meta)}
                if keep_lanes:
                    rows = np.asarray(meta["h_samples"], dtype=np.float64)
                    record.update(pred_lanes=_compact(pred, rows), gt_lanes=_compact(gt, rows))
                handle.write(json.dumps(record) + "\n")
            handle.flush()
            bar.update(len(preds))
    bar.close()
    return out_path


def _drop_torn_tail(path: Path) -> None:
    """Cut a last line an interruption left without its newline, so appended lines start clean."""
    if not path.exists():
        return
    data = path.read_bytes()
    if data and not data.endswith(b"\n"):
        path.write_bytes(data[: data.rfind(b"\n") + 1])


LANE_FIELDS = ("pred_lanes", "gt_lanes")


def read_records(path: str | Path, keep_lanes: bool = True, lanes_for: set[str] | None = None) -> list[dict]:
    """All complete per-image records of a results file.

    keep_lanes=False drops the stored lanes (most of a record's size) except for the keys in
    `lanes_for`, so tables over tens of thousands of images stay small in memory.
    """
    records = []
    with open(path, encoding="utf-8") as handle:
        for line in handle:
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                continue
            if not keep_lanes and record.get("key") not in (lanes_for or ()):
                for field in LANE_FIELDS:
                    record.pop(field, None)
            records.append(record)
    return records


def _progress(total: int, initial: int, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, unit="img", desc="evaluate", disable=not enabled)
