"""Which LaneATT anchors the training lanes use, and the top-k of them the head keeps.

The official LaneATT (lucastabelini/LaneATT) trains on 1,000 of its 2,784 anchors: utils/gen_anchor_mask.py
counts, over the train split's labels, how many images have each anchor matched to one of their lanes
(a positive of lib/models/matching.py at t_pos = 30 px, in save_mask), and lib/models/laneatt.py keeps the
`topk_anchors` most used, most used first (argsort of the counts, descending). Here the counts come from the
train split the run actually uses (simulated scenes, TuSimple or CULane labels), before the first step.

Anchors with equal counts (TIE_ORDERS): counted here, the lower anchor index first ("index", a stable sort); read
from an official frequency file, in the order ``torch.argsort(counts, descending=True)`` gives on the torch that
runs ("torch"), as the official model picks them (lib/models/laneatt.py l. 52). That sort is not stable and its
tie order is the sort kernel's: the published weights were trained under torch 1.6, whose order no current torch
reproduces, so on a file with ties in its top 1,000 (the published TuSimple file has them) the anchors kept can
differ from the ones those weights were trained with.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
import torch

from lanevil_train.lanes import lane_extent_problem
from lanevil_train.models.laneatt.anchors import TARGET_META, encode_lanes
from lanevil_train.models.losses import anchor_target_distances

log = logging.getLogger(__name__)

FREQUENCY_FILE = "laneatt_anchor_frequency.npz"


def anchor_use_frequency(
    anchor_xs: torch.Tensor,
    anchor_starts: torch.Tensor,
    lane_sets: Iterable[list[np.ndarray]],
    image_size: tuple[int, int],
    n_offsets: int,
    pos_threshold: float,
    total: int | None = None,
    scale: str = "last_pixel",
) -> np.ndarray:
    """Per anchor, in how many images it is a positive (mean x distance to one of the image's lanes, over their
    common rows, below pos_threshold pixels): the official get_anchors_use_frequency. lane_sets yields each
    image's lanes in input pixels; total (their number, if known) only paces the progress log; scale: the anchors'
    rows (anchors.FRACTION_SCALES)."""
    counts = np.zeros(len(anchor_starts), dtype=np.int64)
    started, next_report = time.monotonic(), 10.0
    for done, lanes in enumerate(lane_sets, start=1):
        if lanes:
            t = torch.from_numpy(encode_lanes(lanes, image_size, n_offsets, max(1, len(lanes)), scale))[None].float()
            dist = anchor_target_distances(anchor_xs, anchor_starts, t[..., 0], t[..., 1], t[..., 2],
                                           t[..., TARGET_META:])
            counts += (dist[0].min(dim=-1).values < pos_threshold).numpy()
        if time.monotonic() - started > next_report:  # a slow split (rendered scenes) shows it is moving
            log.info("LaneATT anchor frequency: %d%s train images", done, f"/{total}" if total else "")
            next_report += 10.0
    return counts


TIE_ORDERS = ("index", "torch")


def top_anchors(frequency: np.ndarray, topk: int, ties: str = "index") -> np.ndarray:
    """Indices of the topk most used anchors, most used first; equal counts ordered as `ties` says (TIE_ORDERS:
    "index" the lower anchor index first, "torch" as the official's torch.argsort(descending=True))."""
    if ties not in TIE_ORDERS:
        raise ValueError(f"top_anchors: ties={ties!r}, expected one of {', '.join(TIE_ORDERS)}")
    frequency = np.asarray(frequency)
    if ties == "torch":
        order = torch.argsort(torch.from_numpy(frequency), descending=True).numpy()
    else:
        order = np.argsort(-frequency, kind="stable")
    return order[:topk].astype(np.int64)


def train_lane_sets(dataset, input_size: tuple[int, int], crop_top: float = 0.0) -> Iterator[list[np.ndarray]]:
    """Each train image's lanes in input pixels: its top crop_top cut, then resized to input_size, as the
    datamodule feeds the head (without augmentation). Record datasets (TuSimple, CULane: a `.records` list)
    are read from their labels alone, at the first image's size (a record whose lanes do not fit it has its own
    image read); other datasets (simulated scenes) are read item by item."""
    from lanevil_train.data.formats.images import load_image  # here: models/ import data/ only when reading it

    records = getattr(dataset, "records", None)
    if records:
        size = load_image(records[0]["image_path"]).shape[:2]
        for record in records:
            lanes = [np.asarray(lane, dtype=np.float64) for lane in record.get("lanes") or []]
            own = size
            if any(lane_extent_problem(lane, *size) for lane in lanes):
                own = load_image(record["image_path"]).shape[:2]
            yield input_lanes(lanes, own, input_size, crop_top)
    else:
        for index in range(len(dataset)):
            sample = dataset[index]
            yield input_lanes(sample["lanes"], sample["image"].shape[:2], input_size, crop_top)


def input_lanes(lanes: list[np.ndarray], image_hw: tuple[int, int], input_size: tuple[int, int],
                crop_top: float) -> list[np.ndarray]:
    """Lanes of an (h, w) image in the network input's pixels: the top rows cut, clipped to the image, resized."""
    from lanevil_train.data.transforms import clip_lane_to_image, crop_rows

    h, w = image_hw
    rows = crop_rows(crop_top, h)
    scale = np.array([input_size[1] / w, input_size[0] / (h - rows)])
    out = []
    for lane in lanes:
        lane = np.asarray(lane, dtype=np.float64).reshape(-1, 2)
        lane = lane[lane[:, 1] >= rows] - np.array([0.0, rows])
        lane = clip_lane_to_image(lane, h - rows, w)
        if len(lane) >= 2:
            out.append(lane * scale)
    return out


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
