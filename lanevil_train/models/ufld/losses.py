"""UFLD's losses on the group classification logits (B, num_cells + 1, num_rows, num_lanes), each per image (B,).

The last class (index num_cells) is "no lane". The paper's total is L_cls + alpha * (L_sim + lambda * L_shp) +
beta * L_seg; the weights are the head's.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from lanevil_train.models.losses import focal_loss


def classification_loss(logits: torch.Tensor, labels: torch.Tensor, gamma: float = 2.0) -> torch.Tensor:
    """Softmax focal loss over the num_cells + 1 classes of every (row, lane), averaged per image.

    The paper writes cross-entropy; the official code uses this focal loss (gamma 2, no alpha); gamma 0 is
    cross-entropy. logits (B, C+1, R, L), labels (B, R, L) class indices -> (B,).
    """
    per = focal_loss(logits.permute(0, 2, 3, 1), labels, alpha=1.0, gamma=gamma)  # (B, R, L)
    return per.flatten(1).mean(dim=1)


def similarity_loss(logits: torch.Tensor) -> torch.Tensor:
    """The official similarity loss (cfzd/Ultra-Fast-Lane-Detection, utils/loss.py `ParsingRelationLoss`): the
    differences of the raw logits of neighbouring row anchors, every class ("no lane" included), under smooth L1
    (beta 1) against 0, averaged over every element; here per image, so the batch mean equals the official's.

    The paper writes the L1 distance between the rows' softmax distributions; that version rewards spreading each
    distribution (flat rows are alike), which lets "no lane" win the arg-max, and in our head-only fits it lost most
    rows. logits (B, C+1, R, L) -> (B,).
    """
    diff = logits[:, :, :-1].float() - logits[:, :, 1:].float()  # (B, C+1, R-1, L)
    return F.smooth_l1_loss(diff, torch.zeros_like(diff), reduction="none", beta=1.0).flatten(1).mean(dim=1)


def expected_locations(logits: torch.Tensor, local_width: int | None = None,
                       dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """The expected cell index (B, R, L): softmax over the num_cells cells (the "no lane" class left out), then
    sum_k k * prob_k, k from 0 (the paper's Loc, in cell units; as the official TuSimple writer,
    evaluation/eval_wrapper.py `generate_tusimple_lines`; codec.cell_to_x maps it to pixels).

    `local_width` k: the softmax is taken over the cells within k of the arg-max cell only, UFLD v2's decoding
    (evaluation/eval_wrapper.py `generate_lines_local`, local_width = 1), so a flat distribution no longer pulls
    the position towards the image centre as the expectation over all cells does.

    The softmax is taken in float32; `dtype` float64 sums the weighted indices in double precision, as the
    official writers (codec.py), whose whole-pixel x a float32 sum could move across a rounding boundary."""
    cells = logits[:, :-1].float()
    index = torch.arange(cells.shape[1], device=cells.device).view(1, -1, 1, 1)
    if local_width is not None:
        outside = (index - cells.argmax(dim=1, keepdim=True)).abs() > int(local_width)
        cells = cells.masked_fill(outside, float("-inf"))
    prob = torch.softmax(cells, dim=1).to(dtype)
    return (prob * index.to(dtype)).sum(dim=1)


def shape_loss(logits: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """The paper's shape loss: |(Loc_j - Loc_{j+1}) - (Loc_{j+1} - Loc_{j+2})|, the second-order difference of
    the expected locations over three consecutive row anchors, averaged per image.

    Only triples whose three rows all hold the ground-truth lane count (labels != no lane): elsewhere the
    expected location has no meaning. The paper's sum runs over every row, and the official code over the
    upper half of the rows unmasked (with weight 0 in its configs). An image without such triples gives 0.
    """
    no_lane = logits.shape[1] - 1
    loc = expected_locations(logits)  # (B, R, L)
    second = (loc[:, :-2] - 2 * loc[:, 1:-1] + loc[:, 2:]).abs()  # (B, R-2, L)
    present = labels != no_lane
    valid = (present[:, :-2] & present[:, 1:-1] & present[:, 2:]).to(second.dtype)
    return (second * valid).flatten(1).sum(dim=1) / valid.flatten(1).sum(dim=1).clamp(min=1)


def segmentation_loss(seg_logits: torch.Tensor, seg_target: torch.Tensor) -> torch.Tensor:
    """Cross-entropy of the aux segmentation (B, L+1, h, w) against the class-index map (B, h, w), per image.

    The logits are resized (bilinear) to the target's size when they differ (backbones that floor odd sizes)."""
    if seg_logits.shape[-2:] != seg_target.shape[-2:]:
        seg_logits = F.interpolate(seg_logits, size=seg_target.shape[-2:], mode="bilinear", align_corners=False)
    return F.cross_entropy(seg_logits.float(), seg_target.long(), reduction="none").flatten(1).mean(dim=1)
