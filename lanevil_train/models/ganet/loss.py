"""GANet losses (the official ``LaneLossAggress`` terms), each as a per-image sum over a batch normaliser.

The official normalises each term over the whole batch (the focal loss by the batch's keypoint count, the L1
terms by its masked cells, the LFA term by its element count); here every term is returned per image as
B x (the image's sum) / (the batch's normaliser), so its batch mean is the official value and an image's entry
is its share (hard-example defenses rank images by it).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from lanevil_train.models.matching import match

HEAT_EPS = 1e-4  # the official clamps the sigmoid heatmap to [1e-4, 1 - 1e-4]


def heatmap_focal_loss(heat: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """CenterNet's penalty-reduced focal loss (the official ``_neg_loss``), per image (B,):
    -[sum_pos (1-p)^2 log p + sum_neg (1-y)^4 p^2 log(1-p)] / N_pos, positives where the target is 1 and N_pos
    the batch's positive count (at least 1; the official returns 0 for a batch with 2 positives or fewer)."""
    p = heat.float().clamp(HEAT_EPS, 1 - HEAT_EPS)
    pos = target.eq(1).float()
    neg = 1.0 - pos
    pos_term = torch.log(p) * (1 - p).pow(2) * pos
    neg_term = torch.log(1 - p) * p.pow(2) * (1 - target).pow(4) * neg
    per_image = -(pos_term + neg_term).flatten(1).sum(1)
    return per_image * heat.shape[0] / pos.sum().clamp(min=1)


def masked_l1(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, per_channel: bool) -> torch.Tensor:
    """The official ``RegL1KpLoss`` per image (B,): sum |pred - target| over the masked cells, divided by the
    batch's count of masked cells (per_channel=False: the (B, 1, h, w) mask counted once, the error term) or of
    masked entries (per_channel=True: the mask repeated over the channels, the offset term)."""
    m = mask.float().expand_as(pred)
    per_image = ((pred.float() - target.float()).abs() * m).flatten(1).sum(1)
    count = (m if per_channel else mask.float()).sum()
    return per_image * pred.shape[0] / count.clamp(min=1)


def lfa_matches(points: torch.Tensor, gt: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The official ``LaneAssigner``: at the cell of each ground-truth lane point, the K points the LFA predicts
    there ((B, 2K, h, w) offsets from the cell, x then y per point) are matched one-to-one to the lane's G points
    (B, L, G, 2) by the Hungarian method on squared distances. Returns the predicted points (N, K, 2) and their
    matched targets (N, K, 2), one row per (image, valid lane, lane point)."""
    b, k2, h, w = points.shape
    k = k2 // 2
    lanes_b, lanes_l = torch.nonzero(valid > 0, as_tuple=True)
    if len(lanes_b) == 0:
        return points.new_zeros((0, k, 2)), points.new_zeros((0, k, 2))
    lane_gt = gt[lanes_b, lanes_l].float()  # (M, G, 2)
    g = lane_gt.shape[1]
    cx = lane_gt[..., 0].round().long().clamp(0, w - 1)
    cy = lane_gt[..., 1].round().long().clamp(0, h - 1)
    image = lanes_b[:, None].expand(-1, g)
    offs = points.reshape(b, k, 2, h, w).permute(0, 3, 4, 1, 2)[image, cy, cx]  # (M, G, K, 2)
    pred = offs + torch.stack([cx, cy], dim=-1)[:, :, None, :].to(offs.dtype)
    cost = ((pred[:, :, :, None, :] - lane_gt[:, None, None, :, :]) ** 2).sum(-1)  # (M, G, K, G)
    cost_np = cost.detach().cpu().numpy().reshape(-1, k, g)
    chosen = np.empty((cost_np.shape[0], k), dtype=np.int64)
    for i, c in enumerate(cost_np):
        rows, cols = match(c)
        chosen[i, rows] = cols
    chosen_t = torch.from_numpy(chosen).to(gt.device).reshape(len(lanes_b), g, k)
    lane_index = torch.arange(len(lanes_b), device=gt.device)[:, None, None]
    target = lane_gt[lane_index, chosen_t]  # (M, G, K, 2)
    return pred.reshape(-1, k, 2), target.reshape(-1, k, 2)


def lfa_loss(points: torch.Tensor, gt: torch.Tensor, valid: torch.Tensor, beta: float = 1.0 / 9.0) -> torch.Tensor:
    """The LFA auxiliary loss per image (B,): smooth L1 (the official beta 1/9) between the predicted sampling
    points and their matched lane points, over the batch's elements (the official averages over every lane slot,
    padding included; here over the real lanes only)."""
    b = points.shape[0]
    pred, target = lfa_matches(points, gt, valid)
    if len(pred) == 0:
        return points.sum() * 0.0 + points.new_zeros(b)
    per_row = F.smooth_l1_loss(pred.float(), target, reduction="none", beta=beta).flatten(1).sum(1)
    g = gt.shape[2]
    row_image = torch.nonzero(valid > 0, as_tuple=True)[0].repeat_interleave(g)
    per_image = torch.zeros(b, device=points.device, dtype=per_row.dtype).index_add(0, row_image, per_row)
    return per_image * b / pred.numel()
