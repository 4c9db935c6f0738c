"""Lane NMS in plain torch (CPU and GPU alike; no compiled extension).

Semantics of the official LaneATT CUDA kernel: proposals are visited by descending score; one
is suppressed when its mean |x| distance to an already kept proposal, over the rows both
cover, is below the threshold. Proposals with no common row never suppress each other.
"""

from __future__ import annotations

import torch


def lane_ends(starts: torch.Tensor, lengths: torch.Tensor, n_rows: int) -> torch.Tensor:
    """Last row of each proposal: start + round(length) - 1, capped at the top row (n_rows - 1)."""
    return torch.clamp(starts.long() + torch.floor(lengths.float() + 0.5).long() - 1, max=n_rows - 1)


def lane_distances(xs: torch.Tensor, starts: torch.Tensor, ends: torch.Tensor, i: int) -> torch.Tensor:
    """Mean |x_i - x_j| over the rows that proposal i and every proposal j share; +inf if none."""
    n_rows = xs.shape[1]
    lo = torch.maximum(starts, starts[i])
    hi = torch.minimum(ends, ends[i])
    rows = torch.arange(n_rows, device=xs.device)
    common = (rows[None, :] >= lo[:, None]) & (rows[None, :] <= hi[:, None])
    dist = ((xs - xs[i : i + 1]).abs() * common).sum(dim=1)
    count = (hi - lo + 1).clamp(min=0)
    return torch.where(count > 0, dist / count.clamp(min=1), torch.full_like(dist, float("inf")))


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
    if n == 0:
        return torch.zeros(0, dtype=torch.long, device=xs.device)
    order = torch.argsort(scores, descending=True, stable=True)
    xs = xs[order].float()
    starts = starts[order].long()
    ends = lane_ends(starts, lengths[order], xs.shape[1])
    alive = torch.ones(n, dtype=torch.bool, device=xs.device)
    kept: list[int] = []
    limit = n if top_k is None else top_k
    alive_cpu = alive.cpu()
    i = 0
    while len(kept) < limit:
        # next surviving proposal in score order
        while i < n and not bool(alive_cpu[i]):
            i += 1
        if i >= n:
            break
        kept.append(i)
        alive[i] = False
        alive &= ~(lane_distances(xs, starts, ends, i) < threshold)
        alive_cpu = alive.cpu()
        i += 1
    return order[torch.tensor(kept, dtype=torch.long, device=xs.device)]
