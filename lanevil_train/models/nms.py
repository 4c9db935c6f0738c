"""Lane NMS in plain torch (CPU and GPU alike; no compiled extension).

Semantics of the official LaneATT CUDA kernel: proposals are visited by descending score; one
is suppressed when its mean |x| distance to an already kept proposal, over the rows both
cover, is below the threshold. Proposals with no common row never suppress each other.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F


def lane_ends(starts: torch.Tensor, lengths: torch.Tensor, n_rows: int) -> torch.Tensor:
    """Last row of each proposal: start + round(length) - 1, capped at the top row (n_rows - 1)."""
    return torch.clamp(starts.long() + torch.floor(lengths.float() + 0.5).long() - 1, max=n_rows - 1)


def lane_nms(
    xs: torch.Tensor,
    starts: torch.Tensor,
    lengths: torch.Tensor,
    scores: torch.Tensor,
    threshold: float,
    top_k: int | None = None,
) -> torch.Tensor:
    """Indices (into the inputs, by descending score) of the proposals kept by greedy lane NMS.

    xs: (N, S) x per row; starts: (N,) first row; lengths: (N,) rows (rounded as the official);
    threshold: mean x distance in the units of xs; top_k: keep at most this many.
    """
    n = xs.shape[0]
    if xs.ndim != 2 or starts.shape != (n,) or lengths.shape != (n,) or scores.shape != (n,):
        raise ValueError(
            f"lane_nms: expected xs (N, S) and starts/lengths/scores (N,), got {tuple(xs.shape)}, "
            f"{tuple(starts.shape)}, {tuple(lengths.shape)}, {tuple(scores.shape)}"
        )
    return _greedy_keep(xs, starts, lengths, scores, threshold, top_k)


def _suppression_matrix(xs: torch.Tensor, starts: torch.Tensor, ends: torch.Tensor, threshold: float,
                        chunks: int = 2) -> torch.Tensor:
    """(N, N) bool, symmetric: whether proposals i and j are closer than threshold (mean |x| over their common
    rows), for one image.

    Computing every pair over every row costs N^2 x S; instead a lower bound of each pair's distance comes from
    prefix sums (per block of rows, |sum of x_i - x_j| <= sum of |x_i - x_j|), and only the pairs that bound
    leaves under the threshold (neighbours, a few crossing pairs) are measured row by row."""
    n, n_rows = xs.shape
    prefix = F.pad(torch.cumsum(xs, dim=1), (1, 0))  # (N, S+1): prefix[i, r] = sum of x_i over rows < r
    lo = torch.maximum(starts[:, None], starts[None, :])
    hi = torch.minimum(ends[:, None], ends[None, :]) + 1  # exclusive
    count = hi - lo
    bound = torch.zeros(n, n, device=xs.device)
    edges = torch.linspace(0, n_rows, chunks + 1).round().long().tolist()
    for c0, c1 in zip(edges[:-1], edges[1:]):
        a = lo.clamp(c0, c1)
        b = torch.maximum(hi.clamp(c0, c1), a)
        block = torch.gather(prefix, 1, b) - torch.gather(prefix, 1, a)  # [i, j]: sum of x_i over the block
        bound += (block - block.T).abs()
    limit = threshold * count.clamp(min=1)
    candidate = torch.triu((count > 0) & (bound < limit), diagonal=1)
    i, j = torch.nonzero(candidate, as_tuple=True)
    rows = torch.arange(n_rows, device=xs.device)
    common = (rows >= lo[i, j][:, None]) & (rows < hi[i, j][:, None])
    dist = ((xs[i] - xs[j]).abs() * common).sum(dim=1)
    close = torch.zeros(n, n, dtype=torch.bool, device=xs.device)
    close[i, j] = dist < limit[i, j]
    return close | close.T


def lane_nms_batched(
    xs: torch.Tensor,
    starts: torch.Tensor,
    lengths: torch.Tensor,
    scores: torch.Tensor,
    threshold: float,
    top_k: int | None = None,
) -> torch.Tensor:
    """Which proposals greedy lane NMS keeps, per image of a batch: a (B, N) bool mask.

    The rule of lane_nms (xs: (B, N, S); starts: (N,) or (B, N); lengths and scores: (B, N)), fast for
    the many proposals of training: LaneATT runs it on every anchor's proposal (15 px, top 3,000, no
    score threshold) and computes its loss on those kept.
    """
    if xs.ndim != 3 or lengths.shape != xs.shape[:2] or scores.shape != xs.shape[:2]:
        raise ValueError(
            f"lane_nms_batched: expected xs (B, N, S) and lengths/scores (B, N), got {tuple(xs.shape)}, "
            f"{tuple(lengths.shape)}, {tuple(scores.shape)}"
        )
    keep = torch.zeros(xs.shape[:2], dtype=torch.bool, device=xs.device)
    starts = starts.long().expand(xs.shape[:2])
    for k in range(xs.shape[0]):
        keep[k, _greedy_keep(xs[k], starts[k], lengths[k], scores[k], threshold, top_k)] = True
    return keep


def _greedy_keep(xs: torch.Tensor, starts: torch.Tensor, lengths: torch.Tensor, scores: torch.Tensor,
                 threshold: float, top_k: int | None) -> torch.Tensor:
    """One image's kept indices, by descending score: proposals are visited by score, and a kept one removes those
    closer to it than the threshold (the suppression matrix decides "close" for every pair at once)."""
    n = xs.shape[0]
    if n == 0:
        return torch.zeros(0, dtype=torch.long, device=xs.device)
    order = torch.argsort(scores, descending=True, stable=True)
    ordered_starts = starts[order].long()
    ends = lane_ends(ordered_starts, lengths[order], xs.shape[1])
    close = _suppression_matrix(xs[order].float(), ordered_starts, ends, threshold).cpu().numpy()
    limit = n if top_k is None else top_k
    removed = np.zeros(n, dtype=bool)
    kept: list[int] = []
    for i in range(n):
        if removed[i]:
            continue
        kept.append(i)
        if len(kept) == limit:
            break
        removed |= close[i]
    return order[torch.as_tensor(kept, dtype=torch.long, device=xs.device)]


def prune_lanes(confidence: np.ndarray, present: np.ndarray, max_lanes: int | None) -> np.ndarray:
    """present (B, L) limited to max_lanes per image as the official lane_pruning: while an image has more, every
    present slot at its lowest confidence is dropped (equal confidences together). None: unchanged."""
    present = np.array(present, dtype=bool)
    if max_lanes is None:
        return present
    for conf, keep in zip(np.asarray(confidence), present):
        while keep.sum() > max_lanes:
            keep &= conf != conf[keep].min()
    return present
