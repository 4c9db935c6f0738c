"""LaneFormer targets, lane assembly and set loss (Han et al., "Laneformer: Object-aware Row-Column Transformers
for Lane Detection", AAAI 2022).

The paper's lane: a start y, an end y and the x of the lane at N fixed rows (the rows of LaneATT / CLRNet:
``N`` rows evenly from the bottom row, y = H-1, to the top row, y = 0). Each query predicts a lane / background
class and that representation; predictions are matched one to one to the ground-truth lanes (DETR's Hungarian
matching, through ``models.matching.match``) with the cost

    C = -w_cls * p(lane) + w_x * mean_rows |x - x*| + w_y * (|s - s*| + |e - e*|),

and the matched pairs pay cross entropy (the background class weighted by ``eos_coef``, DETR's no-object
weight), L1 on x at the lane's rows and L1 on its start and end y. All coordinates are fractions of the image:
x / (W - 1), y / (H - 1).

Where we had to choose (the paper does not say, or we could not read it): the start y is the lane's lowest
point (largest y), the end y its highest; x is supervised at the rows between them plus one row beyond each end
(extrapolated straight from the lane's two end points), so that decoding can place the exact end points by
interpolation; the x cost and loss are the mean over those rows (every lane counts alike, whatever its
length); the weights default to DETR's (class 1, coordinates 5, no-object 0.1); the regression terms are
normalised by each image's number of lanes (DETR divides by the batch's), so that ``per_sample`` is each
image's own loss and ``loss`` their mean.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from lanevil_train.lanes import as_lane, lane_x_at
from lanevil_train.models.matching import match
from lanevil_train.models.rows import row_ys

# target layout of "lanes": [valid, start_y, end_y, x_0 .. x_{N-1}] (fractions of the image), and "x_mask"
TARGET_META = 3


def _extrapolate(p0: np.ndarray, p1: np.ndarray, y: float) -> float:
    """x at row y on the straight line through points p0, p1 (distinct y)."""
    return float(p0[0] + (y - p0[1]) * (p1[0] - p0[0]) / (p1[1] - p0[1]))


def encode_lane(lane: np.ndarray, image_size: tuple[int, int], num_points: int):
    """One lane (input pixels) -> (start_y px, end_y px, x per row px, mask per row), or None when it has fewer
    than two distinct rows or no point inside the image."""
    h, w = image_size
    lane = as_lane(lane)
    _, first = np.unique(lane[:, 1], return_index=True)
    lane = lane[np.sort(first)]  # distinct y, still descending
    inside = (lane[:, 0] >= 0) & (lane[:, 0] <= w - 1) & (lane[:, 1] >= 0) & (lane[:, 1] <= h - 1)
    if len(lane) < 2 or not inside.any():
        return None
    ys = row_ys(h, num_points)
    start, end = min(lane[0, 1], h - 1.0), max(lane[-1, 1], 0.0)
    if start <= end:
        return None
    xs = np.zeros(num_points)
    mask = (ys >= end) & (ys <= start)
    xs[mask] = lane_x_at(lane, ys[mask])
    below = np.nonzero(ys > start)[0]
    if len(below):  # the row just below the start (rows run bottom first, so the last of these)
        k = below[-1]
        xs[k], mask[k] = _extrapolate(lane[0], lane[1], ys[k]), True
    above = np.nonzero(ys < end)[0]
    if len(above):  # the row just above the end
        k = above[0]
        xs[k], mask[k] = _extrapolate(lane[-1], lane[-2], ys[k]), True
    return start, end, xs, mask


def encode_lanes(lanes: list[np.ndarray], image_size: tuple[int, int], num_points: int,
                 max_lanes: int) -> dict[str, np.ndarray]:
    """Ground-truth lanes (input pixels) -> {"lanes": float32 (max_lanes, 3 + num_points) rows [valid, start_y,
    end_y, xs] in fractions of the image, "x_mask": float32 (max_lanes, num_points), 1 at the supervised rows}.
    Lanes that do not enter the image are dropped; more than max_lanes left is an error."""
    h, w = image_size
    rows = [enc for enc in (encode_lane(np.asarray(lane, dtype=np.float64), image_size, num_points)
                            for lane in lanes) if enc is not None]
    if len(rows) > max_lanes:
        raise ValueError(f"encode: {len(rows)} lanes inside the {w}x{h} image but max_lanes={max_lanes}; raise the "
                         f"head's max_lanes")
    out = np.zeros((max_lanes, TARGET_META + num_points), dtype=np.float32)
    mask = np.zeros((max_lanes, num_points), dtype=np.float32)
    for i, (start, end, xs, m) in enumerate(rows):
        out[i, :TARGET_META] = (1.0, start / (h - 1), end / (h - 1))
        out[i, TARGET_META:] = np.where(m, xs / (w - 1), 0.0)
        mask[i] = m
    return {"lanes": out, "x_mask": mask}


def assemble_lane(xs: np.ndarray, start: float, end: float, ys: np.ndarray, image_size: tuple[int, int]):
    """One prediction (x per row and start / end y, all pixels; ys the rows, bottom first) -> a lane (N, 2), y
    descending: the rows in [end, start] plus the two end points (x interpolated between their neighbouring
    rows), only the points inside the image; None if fewer than two are left."""
    h, w = image_size
    start, end = min(float(start), h - 1.0), max(float(end), 0.0)
    if not start > end:
        return None
    keep = (ys >= end) & (ys <= start)
    asc = slice(None, None, -1)  # ys run bottom (large y) first; np.interp wants them ascending
    ends_x = np.interp([start, end], ys[asc], xs[asc])
    pts_y = np.concatenate([[start], ys[keep], [end]])
    pts_x = np.concatenate([[ends_x[0]], xs[keep], [ends_x[1]]])
    ok = (pts_x >= 0) & (pts_x <= w - 1)
    pts = np.stack([pts_x[ok], pts_y[ok]], axis=1)
    if len(pts) < 2:
        return None
    pts = as_lane(pts)
    distinct = np.concatenate([[True], np.diff(pts[:, 1]) < -1e-6])  # an end point on a row counts once
    pts = pts[distinct]
    return pts if len(pts) >= 2 else None


# ---------------------------------------------------------------------------------------------------- the loss
def matching_cost(logits: torch.Tensor, start: torch.Tensor, end: torch.Tensor, xs: torch.Tensor,
                  targets: torch.Tensor, x_mask: torch.Tensor, cls_weight: float, x_weight: float,
                  y_weight: float) -> torch.Tensor:
    """The paper's matching cost of every prediction with every target slot: (B, Q, M). logits (B, Q, 2) (class 1
    is lane), start / end (B, Q), xs (B, Q, N); targets (B, M, 3 + N), x_mask (B, M, N)."""
    prob = torch.softmax(logits.float(), dim=-1)[..., 1]  # (B, Q)
    t_xs, m = targets[..., TARGET_META:], x_mask
    rows = m.sum(-1).clamp(min=1)  # (B, M)
    x_cost = ((xs[:, :, None, :] - t_xs[:, None]).abs() * m[:, None]).sum(-1) / rows[:, None]
    y_cost = (start[:, :, None] - targets[:, None, :, 1]).abs() + (end[:, :, None] - targets[:, None, :, 2]).abs()
    return -cls_weight * prob[..., None] + x_weight * x_cost + y_weight * y_cost


def assign(cost: torch.Tensor, valid: torch.Tensor) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per image, (prediction indices, target slot indices) of the minimum-cost matching of the valid slots."""
    out = []
    for b in range(cost.shape[0]):
        slots = torch.nonzero(valid[b] > 0.5).flatten().cpu().numpy()
        pred, col = match(cost[b][:, torch.as_tensor(slots, dtype=torch.long, device=cost.device)])
        out.append((pred, slots[col]))
    return out


def set_loss(logits: torch.Tensor, start: torch.Tensor, end: torch.Tensor, xs: torch.Tensor,
             targets: torch.Tensor, x_mask: torch.Tensor, cls_weight: float, x_weight: float, y_weight: float,
             eos_coef: float) -> dict[str, torch.Tensor]:
    """One decoder layer's loss per image: {"total", "cls", "x", "y"} each (B,) (total = the weighted sum)."""
    b, q = start.shape
    valid = targets[..., 0]
    with torch.no_grad():
        cost = matching_cost(logits.detach(), start.detach(), end.detach(), xs.detach(), targets, x_mask,
                             cls_weight, x_weight, y_weight)
        pairs = assign(cost, valid)
        pos = torch.zeros(b, q, dtype=torch.bool, device=start.device)
        slot = torch.zeros(b, q, dtype=torch.long, device=start.device)
        for i, (pred, tgt) in enumerate(pairs):
            pred_t = torch.as_tensor(pred, dtype=torch.long, device=start.device)
            pos[i, pred_t] = True
            slot[i, pred_t] = torch.as_tensor(tgt, dtype=torch.long, device=start.device)
        matched = torch.gather(targets, 1, slot[..., None].expand(-1, -1, targets.shape[-1]))  # (B, Q, 3 + N)
        m = torch.gather(x_mask, 1, slot[..., None].expand(-1, -1, x_mask.shape[-1]))  # (B, Q, N)
        n_lanes = valid.sum(1).clamp(min=1)
    weight = torch.tensor([eos_coef, 1.0], device=logits.device, dtype=torch.float32)
    labels = pos.long()
    ce = F.cross_entropy(logits.float().transpose(1, 2), labels, reduction="none")  # (B, Q)
    w = weight[labels]
    cls_b = (w * ce).sum(1) / w.sum(1)
    x_l1 = ((xs - matched[..., TARGET_META:]).abs() * m).sum(-1) / m.sum(-1).clamp(min=1)
    y_l1 = (start - matched[..., 1]).abs() + (end - matched[..., 2]).abs()
    x_b = (x_l1 * pos).sum(1) / n_lanes
    y_b = (y_l1 * pos).sum(1) / n_lanes
    total = cls_weight * cls_b + x_weight * x_b + y_weight * y_b
    return {"total": total, "cls": cls_b, "x": x_b, "y": y_b}
