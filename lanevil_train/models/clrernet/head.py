"""CLRerNet head: CLRNet's head (models/clrnet: priors, ROIGather, refinement, codec, NMS) with CLRerNet's LaneIoU as
the assignment cost and the IoU loss (laneiou.py), its dynamic top-k, and its ROI sampling layout.

What differs from CLRNetHead (the facts, with the official file and line, in models/clrernet/__init__.py):

- the loss's IoU term is 1 - LaneIoU (half width ``iou_width``, 7.5 px at 800) instead of 1 - Line IoU;
- the assignment's cost is the focal cost minus ``cost_iou_weight`` x the normalised LaneIoU over the prediction's own
  rows (half width ``cost_iou_width``, 30 px at 800); each lane's k is the sum of its ``max_topk`` largest LaneIoUs at
  ``topk_iou_width`` (7.5 px), at least ``min_topk``;
- the lane's angle is measured in ``angle_size`` (height, width) of the evaluation's image region (CULane: the
  1640 x 320 crop), not in the input's pixels (null);
- the ROI features are laid out bottom row first and sampled at the mirrored rows (the official's
  ``prior_feat_ys``: ``official_sampling``), which its published weights expect;
- ``lane_points: official`` keeps the rows left of the image (CLRerNet's decoding keeps every row from the start to
  the end).
"""

from __future__ import annotations

import torch

from lanevil_train.models.clrernet.laneiou import LaneIoU, assign
from lanevil_train.models.clrnet.codec import TARGET_META
from lanevil_train.models.clrnet.head import CLRNetHead
from lanevil_train.models.clrnet.loss import clrnet_losses
from lanevil_train.rules import Rule, check_settings, integer, is_list, is_number, null_or, number, ok


def _size_pair() -> Rule:
    return Rule("[height, width], two numbers > 0",
                lambda v: ok(is_list(v) and len(v) == 2 and all(is_number(x) and x > 0 for x in v)))


def official_sampling(n_points: int, sample_points: int) -> tuple[torch.Tensor, torch.Tensor]:
    """CLRerNet's ROI sampling: the rows whose x is sampled, bottom row first (``sample_x_indices`` =
    int(linspace(0, 1) x n_strips)), and the grid_sample y in [-1, 1] of each sample, the official's ``prior_feat_ys``
    = flip(sample_x_indices / n_strips) x 2 - 1: sample j lies at the row n_strips - index[-1 - j] from the bottom,
    the same row as its x where n_strips j / (sample_points - 1) is whole, one row above it elsewhere."""
    index = (torch.linspace(0.0, 1.0, sample_points) * (n_points - 1)).long()
    return index, 2.0 * index.flip(0).float() / (n_points - 1) - 1.0


class CLRerNetHead(CLRNetHead):
    """CLRerNet: CLRNet's prior refinement trained with LaneIoU. forward, encode, decode and the raw outputs are
    CLRNetHead's ({"cls_logits", "lines", "xs"} per refinement stage)."""

    SETTINGS = {**{k: v for k, v in CLRNetHead.SETTINGS.items() if k != "iou_radius"},
                "iou_width": number(0, low_open=True),
                "cost_iou_width": number(0, low_open=True),
                "topk_iou_width": number(0, low_open=True),
                "angle_size": null_or(_size_pair()),
                "cost_iou_weight": number(0),
                "max_topk": integer(1),
                "min_topk": integer(1)}
    OFFICIAL_KEEPS_LEFT = True

    def __init__(self, in_channels: list[int], in_strides: list[int], image_size: tuple[int, int],
                 num_points: int = 72, num_priors: int = 192, refine_layers: int = 3, sample_points: int = 36,
                 fc_hidden_dim: int = 64, num_fc: int = 2, max_lanes: int = 4, reference_width: float = 800.0,
                 iou_width: float = 7.5, cost_iou_width: float = 30.0, topk_iou_width: float = 7.5,
                 angle_size: tuple[float, float] | None = (320.0, 1640.0), cost_iou_weight: float = 3.0,
                 max_topk: int = 4, min_topk: int = 1, cls_loss_weight: float = 2.0, xyt_loss_weight: float = 0.2,
                 iou_loss_weight: float = 4.0, focal_alpha: float = 0.25, focal_gamma: float = 2.0,
                 seg_loss_weight: float = 0.0, seg_background_weight: float = 0.4, seg_lane_width: float = 16.0,
                 seg_reference_width: float = 1640.0, seg_lanes: int | None = None,
                 row_span: str = "last_pixel") -> None:
        check_settings(self.SETTINGS, locals(), "model.head")
        if min_topk > max_topk:
            raise ValueError(f"CLRerNetHead: model.head.min_topk={min_topk} must not exceed max_topk={max_topk}")
        super().__init__(in_channels, in_strides, image_size, num_points=num_points, num_priors=num_priors,
                         refine_layers=refine_layers, sample_points=sample_points, fc_hidden_dim=fc_hidden_dim,
                         num_fc=num_fc, max_lanes=max_lanes, reference_width=reference_width,
                         cls_loss_weight=cls_loss_weight, xyt_loss_weight=xyt_loss_weight,
                         iou_loss_weight=iou_loss_weight, focal_alpha=focal_alpha, focal_gamma=focal_gamma,
                         seg_loss_weight=seg_loss_weight, seg_background_weight=seg_background_weight,
                         seg_lane_width=seg_lane_width, seg_reference_width=seg_reference_width, seg_lanes=seg_lanes,
                         row_span=row_span)
        # half widths in input pixels, scaled from reference_width as CLRNet's iou_radius
        self.iou_width = iou_width * self.width_scale
        self.cost_iou_width = cost_iou_width * self.width_scale
        self.topk_iou_width = topk_iou_width * self.width_scale
        self.cost_iou_weight, self.max_topk, self.min_topk = float(cost_iou_weight), int(max_topk), int(min_topk)
        size = None if angle_size is None else (float(angle_size[0]), float(angle_size[1]))
        self.laneiou = LaneIoU.of_input(self.image_size, self.row_span, self.n_strips, size)
        index, grid_y = official_sampling(num_points, sample_points)
        self.sample_index, self.sample_grid_y = index, grid_y  # CLRNetHead's buffers, CLRerNet's layout

    def _stage_losses(self, cls_logits: torch.Tensor, lines: torch.Tensor, xs: torch.Tensor,
                      targets: torch.Tensor) -> dict[str, torch.Tensor]:
        """CLRNet's loss terms with CLRerNet's assignment (laneiou.assign) and 1 - LaneIoU as the IoU term."""
        def assignment(c, li, x, t):
            return assign(c, li, x, t, self.laneiou, self.cost_iou_width, self.topk_iou_width, self.cost_iou_weight,
                          self.max_topk, self.min_topk, meta=TARGET_META)

        def lane_iou(pred, target):
            return self.laneiou(pred, target, self.iou_width)

        return clrnet_losses(cls_logits, lines, xs, targets, self.image_size, self.iou_radius, 1.0 / self.width_scale,
                             self.focal_alpha, self.focal_gamma, meta=TARGET_META, assignment=assignment,
                             lane_iou=lane_iou)
