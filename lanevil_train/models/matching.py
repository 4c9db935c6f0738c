"""One-to-one matching of predicted lanes to ground truth (the Hungarian step of DETR-style heads: BezierLaneNet
and LaneFormer). Each family builds its own cost matrix; this solves it.

``match(cost)`` returns, for a (num_predictions, num_targets) cost, the pairs that minimise the summed cost with
every target matched once (when there are at least as many predictions as targets), as scipy's
``linear_sum_assignment`` solves it exactly.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment


def match(cost) -> tuple[np.ndarray, np.ndarray]:
    """(prediction indices, target indices) of the minimum-cost one-to-one assignment, sorted by target index.

    `cost` is a (P, T) array or tensor (P predictions, T targets; gradients are not followed). An empty side gives
    empty indices. Non-finite costs are an error: they would make the assignment arbitrary.
    """
    cost = cost.detach().float().cpu().numpy() if isinstance(cost, torch.Tensor) else np.asarray(cost, float)
    if cost.ndim != 2:
        raise ValueError(f"cost must be a (predictions, targets) matrix, got shape {cost.shape}")
    if cost.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    if not np.isfinite(cost).all():
        raise ValueError("cost has NaN or infinite entries; a matching over them is arbitrary")
    rows, cols = linear_sum_assignment(cost)
    order = np.argsort(cols)
    return rows[order].astype(np.int64), cols[order].astype(np.int64)


def match_batch(costs: torch.Tensor, counts) -> list[tuple[np.ndarray, np.ndarray]]:
    """`match` per image: `costs` (B, P, T_max), `counts` (B,) the number of real targets of each image (the first
    counts[b] columns of costs[b] are real, the rest padding)."""
    counts = [int(n) for n in (counts.tolist() if isinstance(counts, torch.Tensor) else counts)]
    if len(counts) != costs.shape[0]:
        raise ValueError(f"{len(counts)} target counts for a batch of {costs.shape[0]} cost matrices")
    return [match(costs[b, :, :n]) for b, n in enumerate(counts)]
