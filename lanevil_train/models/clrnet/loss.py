"""CLRNet's Line IoU, its dynamic assignment of priors to lanes and its loss (batched, plain torch).

Everything works on a flat batch of N "images" (the head folds the refinement stages into it), P predictions
and L ground-truth slots (``valid`` marks the filled ones). Distances are input pixels; the official's
thresholds are pixels at its 800 px wide input, so the head scales them by W / reference_width.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F

from lanevil_train.models.losses import focal_loss


def _row_valid(target_xs: torch.Tensor, width: int) -> torch.Tensor:
    """Rows where the ground truth is inside the image (the official's x in [0, W))."""
    return (target_xs >= 0) & (target_xs < width)


def line_iou(pred: torch.Tensor, target: torch.Tensor, width: int, radius: float) -> torch.Tensor:
    """Line IoU of aligned lanes (..., S) -> (...): each x widened by `radius` on both sides, the sum over the
    rows where the target is inside the image of the overlaps over the sum of the unions.

    An overlap is min of the right ends minus max of the left ends, negative when the segments are apart, as the
    official, so the value lies in (-1, 1]: 1 for identical lanes, <= 0 for lanes more than 2 radius apart."""
    valid = _row_valid(target, width)
    overlap = torch.minimum(pred, target) + 2 * radius - torch.maximum(pred, target)
    union = torch.maximum(pred, target) - torch.minimum(pred, target) + 2 * radius
    overlap = torch.where(valid, overlap, torch.zeros_like(overlap))
    union = torch.where(valid, union, torch.zeros_like(union))
    return overlap.sum(-1) / (union.sum(-1) + 1e-9)


def pairwise_line_iou(pred: torch.Tensor, target: torch.Tensor, width: int, radius: float) -> torch.Tensor:
    """Line IoU of every prediction (N, P, S) with every target (N, L, S): (N, P, L)."""
    return line_iou(pred[:, :, None, :], target[:, None, :, :], width, radius)


def normalised_score(cost: torch.Tensor, pair_ok: torch.Tensor) -> torch.Tensor:
    """The official's 1 - c / max(c) + 0.01, the max over each image's valid (prediction, lane) pairs."""
    top = torch.where(pair_ok, cost, torch.zeros_like(cost)).amax(dim=(1, 2), keepdim=True)
    return 1.0 - cost / top.clamp(min=1e-9) + 1e-2


def focal_cost(cls_logits: torch.Tensor, alpha: float = 0.25, gamma: float = 2.0) -> torch.Tensor:
    """The official assignments' focal classification cost of each prediction (N, P) from its logits (N, P, 2): the
    positive and negative focal terms of the sigmoid of the positive logit, positive minus negative (CLRNet's and
    CLRerNet's FocalCost)."""
    prob = cls_logits[..., 1].float().sigmoid()
    eps = 1e-12
    pos_cost = -(prob + eps).log() * alpha * (1 - prob).pow(gamma)
    neg_cost = -(1 - prob + eps).log() * (1 - alpha) * prob.pow(gamma)
    return pos_cost - neg_cost


def dynamic_topk(cost: torch.Tensor, iou: torch.Tensor, valid: torch.Tensor, max_topk: int = 4,
                 min_topk: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """The dynamic top-k assignment of CLRNet and CLRerNet on a cost (N, P, L) and an IoU (N, P, L) matrix: lane l
    takes its k lowest-cost predictions, k = max(min_topk, int(sum of its max_topk largest IoUs, negatives as 0));
    a prediction taken by several lanes keeps the one of lowest cost (the official's matching-matrix row cleared and
    its argmin set). Ties go to the lower prediction index. Returns the positive mask (N, P) and each positive's lane
    index (N, P). `valid` (N, L) marks the filled lane slots; the others take nothing."""
    p = cost.shape[1]
    pair_ok = valid[:, None, :].expand_as(cost)
    cost = torch.where(pair_ok, cost, torch.full_like(cost, float("inf")))
    iou = torch.where(pair_ok, iou.clamp(min=0), torch.zeros_like(iou))
    top_iou = iou.topk(min(max_topk, p), dim=1).values.sum(1)  # (N, L)
    k = torch.where(valid, top_iou.int().clamp(min=min_topk), torch.zeros_like(top_iou, dtype=torch.int32))
    rank = cost.argsort(dim=1, stable=True).argsort(dim=1)  # each prediction's rank for each lane
    chosen = rank < k[:, None, :]
    several = chosen.sum(-1) > 1
    best = F.one_hot(cost.argmin(-1), cost.shape[-1]).bool()
    chosen = torch.where(several[..., None], best, chosen)
    return chosen.any(-1), chosen.float().argmax(-1)


@torch.no_grad()
def assign(cls_logits: torch.Tensor, lines: torch.Tensor, xs: torch.Tensor, targets: torch.Tensor,
           image_size: tuple[int, int], radius: float, n_candidates: int = 4, distance_weight: float = 3.0,
           cls_weight: float = 1.0, meta: int = 5) -> tuple[torch.Tensor, torch.Tensor]:
    """CLRNet's dynamic (SimOTA-like) assignment: a positive mask (N, P) and each positive's lane index (N, P).

    cls_logits (N, P, 2); lines (N, P, >=3) [start_y, start_x (fraction of W-1), theta, ...]; xs (N, P, S)
    pixels; targets (N, L, meta + S) as codec.py encodes them. The cost of a (prediction, lane) pair is
    focal classification cost - distance_weight x (distance score x start-point score x angle score)^2, each
    score 1 - c / max c + 0.01 (mean |x| distance over the lane's rows, start-point distance in pixels, angle
    difference in degrees). Each lane takes its k lowest-cost predictions, k = max(1, int(sum of its
    n_candidates largest Line IoUs, negatives as 0)) (dynamic_topk); a prediction taken by several lanes keeps the
    one of lowest cost (the official at 7269e9d zeroes only the first lane's column there, an indexing slip that
    CLRerNet fixed at 72c6c8c; we clear the row).
    """
    h, w = image_size
    n, p, _ = xs.shape
    valid = targets[..., 0] > 0  # (N, L)
    t_xs = targets[..., meta:]
    pair_ok = valid[:, None, :].expand(n, p, valid.shape[1])

    row_ok = _row_valid(t_xs, w)[:, None]  # (N, 1, L, S)
    diff = (xs[:, :, None, :] - t_xs[:, None, :, :]).abs()
    dist = torch.where(row_ok, diff, torch.zeros_like(diff)).sum(-1) / (row_ok.sum(-1) + 1e-9)
    pred_start = torch.stack([lines[..., 0] * (h - 1), lines[..., 1] * (w - 1)], dim=-1)  # (N, P, 2) pixels
    t_start = torch.stack([targets[..., 1] * (h - 1), targets[..., 2]], dim=-1)  # (N, L, 2)
    start_dist = (pred_start[:, :, None, :] - t_start[:, None, :, :]).norm(dim=-1)
    angle_dist = (lines[..., 2:3] - targets[..., 3][:, None, :]).abs() * 180
    similarity = (normalised_score(dist, pair_ok) * normalised_score(start_dist, pair_ok)
                  * normalised_score(angle_dist, pair_ok))
    cost = -similarity.pow(2) * distance_weight + focal_cost(cls_logits)[..., None] * cls_weight
    iou = pairwise_line_iou(xs, t_xs, w, radius)
    return dynamic_topk(cost, iou, valid, n_candidates)


def clrnet_losses(cls_logits: torch.Tensor, lines: torch.Tensor, xs: torch.Tensor, targets: torch.Tensor,
                  image_size: tuple[int, int], radius: float, px_scale: float, focal_alpha: float = 0.25,
                  focal_gamma: float = 2.0, meta: int = 5, assignment: Callable | None = None,
                  lane_iou: Callable | None = None) -> dict[str, torch.Tensor]:
    """The three loss terms (N,) of each image (one stage's predictions), the official's normalisation.

    cls: softmax focal loss summed over the predictions, over the number of lanes (over 1 without lanes);
    xytl: smooth-L1 of the positives' (start_y in rows, start_x in pixels x px_scale, theta in degrees, length
    in rows; the length target shortened by how far the prediction starts above the lane) averaged over the
    positives; iou: the positives' mean 1 - Line IoU. lines (N, P, 4): [start_y, start_x, theta, length]
    normalised; xs (N, P, S) pixels. Returns cls, xytl, iou and the positive mask.

    Another family of this head (CLRerNet) swaps the assignment and the IoU: `assignment(cls_logits, lines, xs,
    targets) -> (positive mask, lane index)` (default: ``assign`` with `radius`) and `lane_iou(pred_xs, target_xs)
    -> IoU` of aligned lanes (..., S) -> (...) (default: ``line_iou`` with `radius`)."""
    w = image_size[1]
    n_strips = xs.shape[-1] - 1
    targets = targets.float()
    if assignment is None:
        def assignment(c, li, x, t):
            return assign(c, li, x, t, image_size, radius, meta=meta)
    if lane_iou is None:
        def lane_iou(pred, target):
            return line_iou(pred, target, w, radius)
    pos, index = assignment(cls_logits.detach(), lines.detach(), xs.detach(), targets)
    n_lanes = (targets[..., 0] > 0).sum(1).float()
    cls = (focal_loss(cls_logits, pos.long(), focal_alpha, focal_gamma).sum(1) / n_lanes.clamp(min=1))

    matched = torch.gather(targets, 1, index[..., None].expand(-1, -1, targets.shape[-1]))  # (N, P, D)
    with torch.no_grad():
        pred_start = torch.clamp(torch.round(lines[..., 0] * n_strips), 0, n_strips)
        t_start = torch.round(matched[..., 1] * n_strips)
        t_yxtl = torch.stack([matched[..., 1] * n_strips, matched[..., 2] * px_scale, matched[..., 3] * 180,
                              matched[..., 4] - (pred_start - t_start)], dim=-1)
    p_yxtl = torch.stack([lines[..., 0] * n_strips, lines[..., 1] * (w - 1) * px_scale, lines[..., 2] * 180,
                          lines[..., 3] * n_strips], dim=-1)
    n_pos = pos.sum(1).float()
    sl1 = F.smooth_l1_loss(p_yxtl, t_yxtl, reduction="none").sum(-1)
    xytl = (sl1 * pos).sum(1) / (4 * n_pos).clamp(min=1)
    liou = 1.0 - lane_iou(xs, matched[..., meta:])
    iou = (liou * pos).sum(1) / n_pos.clamp(min=1)
    return {"cls": cls, "xytl": xytl, "iou": iou, "pos": pos}


IGNORE_LABEL = 255  # the official's ignore_label: pixels of this class take no part in the segmentation loss


def segmentation_loss(logits: torch.Tensor, target: torch.Tensor, background_weight: float) -> torch.Tensor:
    """The official auxiliary segmentation loss, per image (N,): cross-entropy of the class logits (N, K, H, W)
    against the class map (N, H, W) (0 background, 1.. lane slots, IGNORE_LABEL ignored), each pixel weighted by
    its true class's weight (background_weight for class 0, 1 for the lanes), divided by the sum of those weights:
    torch's NLLLoss(weight) mean, as the official, over each image instead of the whole batch (the per-image
    losses the detector needs; the same for a batch of one). An image with no counted pixel gives 0."""
    k = logits.shape[1]
    weight = torch.ones(k, device=logits.device, dtype=torch.float32)
    weight[0] = background_weight
    target = target.long()
    nll = F.cross_entropy(logits.float(), target, weight=weight, ignore_index=IGNORE_LABEL, reduction="none")
    counted = target != IGNORE_LABEL
    pixel_weight = torch.where(counted, weight[target.clamp(0, k - 1)], torch.zeros_like(nll))
    return nll.flatten(1).sum(1) / pixel_weight.flatten(1).sum(1).clamp(min=1e-9)
