"""Which LaneATT anchors the head keeps, from how often the train split's lanes use each one.

The official LaneATT (lucastabelini/LaneATT) trains on 1,000 of its 2,784 anchors: utils/gen_anchor_mask.py
counts, over the train split's labels, how many images have each anchor matched to one of their lanes
(a positive of lib/models/matching.py at t_pos = 30 px, in save_mask), and lib/models/laneatt.py keeps the
`topk_anchors` most used, most used first (argsort of the counts, descending). Here the counts come from the
train split the run actually uses (simulated scenes, TuSimple or CULane labels), before the first step: the task
counts them (tasks/detector/anchor_use.py, over the lanes data/datasets.py input_lane_sets reads), the head says
which anchors one image's lanes use (LaneATTHead.anchors_used) and takes the counts (LaneATTHead.use_frequency,
which keeps `top_anchors` of them).

Anchors with equal counts (TIE_ORDERS): counted here, the lower anchor index first ("index", a stable sort); read
from an official frequency file, in the order ``torch.argsort(counts, descending=True)`` gives on the torch that
runs ("torch"), as the official model picks them (lib/models/laneatt.py l. 52). That sort is not stable and its
tie order is the sort kernel's: the published weights were trained under torch 1.6, whose order no current torch
reproduces, so on a file with ties in its top 1,000 (the published TuSimple file has them) the anchors kept can
differ from the ones those weights were trained with.
"""

from __future__ import annotations

import numpy as np
import torch

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
