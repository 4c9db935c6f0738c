"""CLRerNet's LaneIoU and its dynamic top-k assignment (batched, plain torch; the facts in models/clrernet/__init__.py).

LaneIoU is CLRNet's Line IoU with a virtual lane width that follows the lane's local angle: at each row the half
width is ``half_width x sqrt(dx^2 + dy^2) / dy``, dx the lane's x change between the row's two neighbours and dy their
height, both measured in the geometry the evaluation sees (``angle_size``: CULane's 1640 x 320 crop below the sky cut,
not the 800 x 320 input), so that a slanted lane is as wide, across it, as a vertical one. Distances are input pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from lanevil_train.models.clrnet.loss import dynamic_topk, focal_cost, normalised_score

MAX_DX = 1e4  # a target's dx above this (angle-geometry px) spans an undefined row: counted as 0 (iou_loss.py:66, 92)


@dataclass(frozen=True)
class LaneIoU:
    """LaneIoU on one input geometry.

    width: the input width (px); a row counts where the target's x lies in [0, width).
    x_scale: angle-geometry pixels per input pixel in x (angle width / input width).
    dy: the height between a row's two neighbours in angle-geometry pixels (2 row steps x angle height / input height).
    """

    width: float
    x_scale: float
    dy: float

    @classmethod
    def of_input(cls, image_size: tuple[int, int], row_span: float, n_strips: int,
                 angle_size: tuple[float, float] | None = None) -> LaneIoU:
        """The geometry of an (H, W) input whose rows span `row_span` px in `n_strips` steps; the angle measured over
        `angle_size` (height, width) of the evaluation's image region, or the input's own pixels (None)."""
        h, w = image_size
        angle_h, angle_w = (h, w) if angle_size is None else angle_size
        return cls(float(w), angle_w / w, 2.0 * row_span / n_strips * angle_h / h)

    def half_widths(self, xs: torch.Tensor, half_width: float, undefined_rows: bool = False) -> torch.Tensor:
        """The virtual half width (px) at each row of lanes xs (..., S), no gradient: half_width x sqrt(dx^2 + dy^2)
        / dy, dx = (x[i+1] - x[i-1]) x x_scale; the first and last rows take their neighbour's. `undefined_rows`
        (targets): a dx above MAX_DX counted 0."""
        xs = xs.detach()
        dx = (xs[..., 2:] - xs[..., :-2]) * self.x_scale
        if undefined_rows:
            dx = torch.where(dx.abs() > MAX_DX, torch.zeros_like(dx), dx)
        inner = half_width * torch.sqrt(dx ** 2 + self.dy ** 2) / self.dy
        return torch.cat([inner[..., :1], inner, inner[..., -1:]], dim=-1)

    def __call__(self, pred: torch.Tensor, target: torch.Tensor, half_width: float,
                 pred_rows: torch.Tensor | None = None) -> torch.Tensor:
        """LaneIoU of lanes pred and target (broadcastable (..., S), px) -> (...): the sum over the rows of the
        overlaps of the widened segments over the sum of their unions, an overlap negative where they are apart.

        Without `pred_rows` only the target's rows inside the image count (the loss, and the assignment's dynamic k).
        With it (a boolean (..., S) of the prediction's own rows: the assignment's cost), a row counts where both
        lanes are inside the image; where only one of them is, its widened segment is added to the union."""
        pred_w = self.half_widths(pred, half_width)
        target_w = self.half_widths(target, half_width, undefined_rows=True)
        overlap = torch.minimum(pred + pred_w, target + target_w) - torch.maximum(pred - pred_w, target - target_w)
        union = torch.maximum(pred + pred_w, target + target_w) - torch.minimum(pred - pred_w, target - target_w)
        target_in = (target >= 0) & (target < self.width)
        if pred_rows is None:
            both = target_in
            extra = torch.zeros_like(union)
        else:
            pred_in = pred_rows & (pred >= 0) & (pred < self.width)
            both = target_in & pred_in
            extra = (torch.where(pred_in & ~target_in, 2 * pred_w, torch.zeros_like(pred_w))
                     + torch.where(target_in & ~pred_in, 2 * target_w, torch.zeros_like(target_w)))
        zero = torch.zeros_like(overlap)
        overlap = torch.where(both, overlap, zero)
        union = torch.where(both, union, zero) + extra
        return overlap.sum(-1) / (union.sum(-1) + 1e-9)


def prediction_rows(lines: torch.Tensor, n_points: int) -> torch.Tensor:
    """The rows (..., S) each prediction covers (lines (..., 4) [start_y, start_x, theta, length], normalised):
    from int(start x n_strips) to int(end x n_strips), end excluded, start = start_y and end = start + length, both
    clamped to [0, 1] (the official's (1 - y0) and its length, dynamic_topk_assigner.py:162-167,
    match_cost.py:189-195)."""
    n_strips = n_points - 1
    start = lines[..., 0].clamp(0, 1)
    end = (start + lines[..., 3]).clamp(0, 1)
    rows = torch.arange(n_points, device=lines.device)
    first = (start * n_strips).long()[..., None]
    last = (end * n_strips).long()[..., None]
    return (rows >= first) & (rows < last)


@torch.no_grad()
def assign(cls_logits: torch.Tensor, lines: torch.Tensor, xs: torch.Tensor, targets: torch.Tensor, geometry: LaneIoU,
           cost_width: float, topk_width: float, cost_weight: float = 3.0, max_topk: int = 4, min_topk: int = 1,
           meta: int = 5) -> tuple[torch.Tensor, torch.Tensor]:
    """CLRerNet's assignment: a positive mask (N, P) and each positive's lane index (N, P).

    cls_logits (N, P, 2); lines (N, P, 4); xs (N, P, S) px; targets (N, L, meta + S) as CLRNet's codec encodes them
    (valid first, x from column `meta`). The cost of a (prediction, lane) pair is the focal classification cost minus
    cost_weight x (1 - (1 - IoU) / max(1 - IoU) + 0.01), IoU the LaneIoU at half width `cost_width` over the
    prediction's own rows (the max over the image's valid pairs); each lane takes its k lowest-cost predictions,
    k = max(min_topk, int(sum of its max_topk largest LaneIoUs at `topk_width` over the lane's rows)), a prediction
    taken by several lanes keeping the one of lowest cost (clrnet.loss.dynamic_topk)."""
    valid = targets[..., 0] > 0  # (N, L)
    pred = xs[:, :, None, :]
    target = targets[..., meta:][:, None, :, :]
    rows = prediction_rows(lines, xs.shape[-1])[:, :, None, :]
    cost_iou = geometry(pred, target, cost_width, pred_rows=rows)  # (N, P, L)
    pair_ok = valid[:, None, :].expand_as(cost_iou)
    cost = -normalised_score(1.0 - cost_iou, pair_ok) * cost_weight + focal_cost(cls_logits)[..., None]
    return dynamic_topk(cost, geometry(pred, target, topk_width), valid, max_topk, min_topk)
