"""Before training: how often the train split's lanes use each anchor of a head that keeps its most used anchors
(LaneATT with anchor_selection=frequency: models/laneatt/frequency.py), counted once per run directory.

The split's lanes come from data/ as the datamodule feeds them to the head, without augmentation
(data/datasets.py input_lane_sets: record datasets from their labels, simulated scenes item by item). The head says
which of its anchors one image's lanes use (`anchors_used`) and takes the counts (`use_frequency`); here they are
summed over the split and kept in the run directory (FREQUENCY_FILE) under a fingerprint of the split and of what
the counting depends on, so a rerun in the same directory reads them back instead of counting again.

A head takes part through `wants_anchor_use()` (whether it still waits for the counts: a checkpoint's anchors are
kept), `anchor_use_settings()` (what its counts depend on besides the split), `anchors_used(lanes)`,
`use_frequency(counts)`, and its `image_size` and `all_anchors`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from lanevil_train.data.datasets import input_lane_sets

log = logging.getLogger(__name__)

FREQUENCY_FILE = "laneatt_anchor_frequency.npz"


def count_anchor_use(head, lane_sets: Iterable[list[np.ndarray]], total: int | None = None) -> np.ndarray:
    """Per anchor of the head's full set, in how many images it is used (head.anchors_used: the official
    get_anchors_use_frequency). lane_sets yields each image's lanes in input pixels; total (their number, if known)
    only paces the progress log."""
    counts = np.zeros(len(head.all_anchors), dtype=np.int64)
    started, next_report = time.monotonic(), 10.0
    for done, lanes in enumerate(lane_sets, start=1):
        if lanes:
            counts += head.anchors_used(lanes)
        if time.monotonic() - started > next_report:  # a slow split (rendered scenes) shows it is moving
            log.info("LaneATT anchor frequency: %d%s train images", done, f"/{total}" if total else "")
            next_report += 10.0
    return counts


def dataset_fingerprint(dataset, input_size: tuple[int, int], crop_top: float, extra: dict) -> str:
    """A short hash naming the train split and geometry a cached frequency was counted for."""
    key_of = getattr(dataset, "item_key", None)
    n = len(dataset)
    ends = [str(key_of(0)), str(key_of(n - 1))] if key_of is not None and n else []
    text = json.dumps({"dataset": type(dataset).__name__, "n": n, "ends": ends, "input_size": list(input_size),
                       "crop_top": float(crop_top), **extra}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def cached_frequency(cache_dir: str | Path | None, fingerprint: str, compute) -> np.ndarray:
    """compute() once per run directory: the counts are kept in cache_dir/FREQUENCY_FILE under fingerprint, so
    a rerun in the same directory (same split and geometry) reads them back instead of counting again."""
    path = None if cache_dir is None else Path(cache_dir) / FREQUENCY_FILE
    if path is not None and path.is_file():
        with np.load(path) as saved:
            if str(saved["fingerprint"]) == fingerprint:
                return saved["frequency"]
    frequency = compute()
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(f"{path.name}.{os.getpid()}.partial.npz")
        np.savez(partial, frequency=frequency, fingerprint=np.array(fingerprint))
        os.replace(partial, path)  # atomic: ranks of a multi-device run may write it at once
    return frequency


def choose_anchors(head, train_dataset, crop_top: float = 0.0, cache_dir=None) -> bool:
    """Count how often the train split's lanes (the images' top crop_top cut, as the model's input) use each of the
    head's anchors and give the counts to the head, which keeps the most used; the counts are cached in cache_dir
    (the run directory). Nothing to do, and False, for a head that chooses no anchors, one whose anchors are all
    kept or chosen already (a checkpoint's), or without a train split."""
    wants = getattr(head, "wants_anchor_use", None)
    if wants is None or not wants() or train_dataset is None:
        return False
    key = dataset_fingerprint(train_dataset, head.image_size, crop_top, head.anchor_use_settings())

    def count():
        log.info("LaneATT: counting how often the %d train images' lanes use each of the %d anchors",
                 len(train_dataset), len(head.all_anchors))
        lanes = input_lane_sets(train_dataset, head.image_size, crop_top)
        return count_anchor_use(head, lanes, total=len(train_dataset))

    head.use_frequency(cached_frequency(cache_dir, key, count))
    return True
