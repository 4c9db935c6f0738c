"""Losses shared by anchor-based lane heads: softmax focal loss and anchor-to-lane matching."""

from __future__ import annotations

import torch
import torch.nn.functional as F

INF_DISTANCE = 1e9


def focal_loss(logits: torch.Tensor, target: torch.Tensor, alpha: float = 0.25, gamma: float = 2.0) -> torch.Tensor:
    """Per-element softmax focal loss, -alpha (1 - p_t)^gamma log p_t (Lin et al.; LaneATT's variant).

    logits: (..., C); target: (...) class indices. Returns a tensor of shape (...).
    """
    log_p = F.log_softmax(logits.float(), dim=-1)
    log_pt = log_p.gather(-1, target.long().unsqueeze(-1)).squeeze(-1)
    pt = log_pt.exp()
    return -alpha * (1.0 - pt).pow(gamma) * log_pt


def anchor_target_distances(
    anchor_xs: torch.Tensor,
    anchor_starts: torch.Tensor,
    target_valid: torch.Tensor,
    target_starts: torch.Tensor,
    target_lengths: torch.Tensor,
    target_xs: torch.Tensor,
) -> torch.Tensor:
    """Mean |x| distance (B, A, L) between each anchor and each target lane over their common rows.

    Common rows run from max(anchor start, target start) to the target's last row, as in the
    official matching; no common row, or an empty target slot, gives INF_DISTANCE.
    """
    n_rows = anchor_xs.shape[1]
    rows = torch.arange(n_rows, device=anchor_xs.device)
    t_end = (target_starts + target_lengths - 1).long()  # (B, L)
    lo = torch.maximum(anchor_starts.long()[None, :, None], target_starts.long()[:, None, :])  # (B, A, L)
    count = (t_end[:, None, :] - lo + 1).clamp(min=0)
    common = (rows >= lo[..., None]) & (rows <= t_end[:, None, :, None])  # (B, A, L, S)
    diff = (anchor_xs[None, :, None, :] - target_xs[:, None, :, :]).abs()
    dist = torch.where(common, diff, torch.zeros_like(diff)).sum(-1) / count.clamp(min=1)
    ok = (count > 0) & (target_valid[:, None, :] > 0)
    return torch.where(ok, dist, torch.full_like(dist, INF_DISTANCE))
