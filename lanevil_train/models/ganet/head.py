"""GANet head (Wang et al., "A Keypoint-based Global Association Network for Lane Detection", CVPR 2022).

Lanes as keypoints: on the stride-8 level a keypoint heatmap (1 channel, sigmoid), the sub-cell error of each
keypoint (2 channels) and, the paper's global association, every keypoint's offset to its lane's start point
(2 channels); decoding groups the keypoints by the start points they point at (codec.py).

The head reads the backbone's C3, C4, C5 and builds GANet's own neck (neck.py, the official DeformFPN): two
self-attention layers with sine position embeddings on C5, which then replaces C5; 1x1 laterals and the top-down
sum; the Lane-aware Feature Aggregator (LFA) on the finest merged lateral, then a 3x3 conv, for the heatmap
branch; the offset and error branches read the merged lateral itself (the official ``dcn_only_cls``). The LFA
predicts K points per location, reads the features there and aggregates them (the official's deformable 1-D
convolution: sum_k W_k f(p_k)); an auxiliary loss pulls the K points onto the ground-truth lane.

Where this differs from the official, and why:
- the LFA's deformable convolution is grid_sample (models/sampling) at the predicted points of a 1x1 projection
  per point, summed: the same function (sampling is linear), exportable to ONNX; its point output starts small
  (normal, std 0.01) instead of xavier, so the first points lie near their location;
- the position embedding is computed for the C5 map's actual size (the official builds it once for its
  configured 320x800 input: the same values there);
- the official's 3x3 output convs of the stride-16 and stride-32 levels, whose outputs nothing reads, are left
  out;
- per-image loss normalisation (loss.py) and the decoding's nearest-centre assignment (codec.py).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from lanevil_train.models.ganet.codec import decode_lanes, encode_targets, heatmap_size
from lanevil_train.models.ganet.loss import heatmap_focal_loss, lfa_loss, masked_l1
from lanevil_train.models.ganet.neck import GANetNeck
from lanevil_train.models.head import LaneHead
from lanevil_train.rules import boolean, check_settings, integer, null_or, number

HEATMAP_BIAS = -2.19  # CenterNet's initial heatmap bias (sigmoid 0.1), the official CtnetHead's


def _branch(c_in: int, hidden: int, out: int) -> nn.Sequential:
    """The official CtnetHead branch: 3x3 conv, ReLU, 1x1 conv."""
    return nn.Sequential(nn.Conv2d(c_in, hidden, 3, padding=1), nn.ReLU(inplace=True), nn.Conv2d(hidden, out, 1))


class GANetHead(LaneHead):
    """GANet on the backbone's maps, finest first (C3, C4, C5 in the paper): its neck (neck.py) merges them
    top-down onto the finest one, whose stride is the heatmap's (8 in the paper)."""

    # The constructor's parameters with a range, and what a good value of each is: checked by the constructor,
    # and by the config check under model.head.* before any work (one place to say it).
    SETTINGS = {
        "max_lanes": integer(1),
        "fpn_channels": integer(2),
        "attention_layers": integer(1),
        "attention_channels": null_or(integer(2)),
        "head_channels": integer(1),
        "lfa_channels": integer(1),
        "lfa_convs": integer(0),
        "lfa_points": integer(1),
        "lfa_gradient_mul": number(0, 1),
        "lfa_gt_points": integer(1),
        "points_per_lane": integer(2),
        "radius": integer(0),
        "top_attention": boolean(),
        "attention_ratio": integer(1),
        "heatmap_loss_weight": number(0),
        "error_loss_weight": number(0),
        "offset_loss_weight": number(0),
        "lfa_loss_weight": number(0),
        "lfa_beta": number(0, low_open=True),
        "reference_width": number(0, low_open=True),
    }

    def __init__(
        self,
        in_channels: list[int],
        in_strides: list[int],
        image_size: tuple[int, int],
        max_lanes: int = 4,
        fpn_channels: int = 64,
        head_channels: int = 64,
        lfa_channels: int = 256,
        lfa_convs: int = 3,
        lfa_points: int = 7,
        lfa_gradient_mul: float = 0.1,
        lfa_gt_points: int = 41,
        points_per_lane: int = 45,
        radius: int = 2,
        top_attention: bool = True,
        attention_layers: int = 2,
        attention_ratio: int = 4,
        attention_channels: int | None = None,
        heatmap_loss_weight: float = 1.0,
        error_loss_weight: float = 1.0,
        offset_loss_weight: float = 0.5,
        lfa_loss_weight: float = 0.2,
        lfa_beta: float = 1.0 / 9.0,
        reference_width: float = 800.0,
    ) -> None:
        check_settings(self.SETTINGS, locals(), "model.head")
        super().__init__(in_channels, in_strides, image_size)
        if lfa_gt_points < lfa_points:
            raise ValueError(f"GANetHead: lfa_gt_points ({lfa_gt_points}) must be >= lfa_points ({lfa_points}): "
                             f"each predicted point is matched to its own lane point")
        channels = int(fpn_channels)
        attended = channels if attention_channels is None else int(attention_channels)
        if top_attention and attended % 2:
            raise ValueError(f"GANetHead: the attention's channels (attention_channels, or fpn_channels when null) "
                             f"must be even with top_attention (the sine position embedding gives half its channels "
                             f"to y, half to x), got {attended}")
        if top_attention and attended // attention_ratio < 1:
            raise ValueError(f"GANetHead: attention_ratio {attention_ratio} leaves no query channels of the "
                             f"attention's {attended}")
        self.max_lanes = int(max_lanes)
        self.stride = self.in_strides[0]
        self.fmap_size = heatmap_size(self.image_size, self.stride)
        self.points_per_lane, self.radius, self.lfa_gt_points = int(points_per_lane), int(radius), int(lfa_gt_points)
        self.lfa_beta = float(lfa_beta)
        self.threshold_scale = self.image_size[1] / float(reference_width)
        weights = {"heatmap": heatmap_loss_weight, "error": error_loss_weight, "offset": offset_loss_weight,
                   "lfa": lfa_loss_weight}
        self.weights = {k: float(v) for k, v in weights.items()}
        self.neck = GANetNeck(self.in_channels, channels, int(attention_layers) if top_attention else 0,
                              int(attention_ratio), int(lfa_channels), int(lfa_convs), int(lfa_points),
                              float(lfa_gradient_mul), attended)
        self.heatmap_head = _branch(channels, head_channels, 1)
        self.offset_head = _branch(channels, head_channels, 2)
        self.error_head = _branch(channels, head_channels, 2)
        # the official CtnetHead: the heatmap's last bias -2.19; every bias of the other branches zero
        nn.init.constant_(self.heatmap_head[-1].bias, HEATMAP_BIAS)
        for branch in (self.offset_head, self.error_head):
            for conv in (branch[0], branch[-1]):
                nn.init.zeros_(conv.bias)

    # ------------------------------------------------------------------ forward
    def forward(self, features: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        """heatmap (B, 1, h, w) in [0, 1]; offsets (B, 2, h, w) to the start point and error (B, 2, h, w), in
        heatmap cells (x, y); in training also lfa_points (B, 2K, h, w), the LFA's point offsets."""
        neck = self.neck(features, self.fmap_size)
        raw = {"heatmap": torch.sigmoid(self.heatmap_head(neck["features"])),
               "offsets": self.offset_head(neck["lateral"]), "error": self.error_head(neck["lateral"])}
        if self.training:
            raw["lfa_points"] = neck["points"]
        return raw

    # ------------------------------------------------------------------ targets
    def encode(self, lanes: list[np.ndarray], meta: dict | None = None) -> dict[str, np.ndarray]:
        """GT lanes (input pixels) -> heatmap, error, offsets, mask, lfa_points, lfa_valid (codec.py)."""
        return encode_targets(lanes, self.image_size, self.stride, self.max_lanes, self.points_per_lane,
                              self.radius, self.lfa_gt_points)

    def loss(self, raw: dict, targets: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """w_point focal(heatmap) + w_error L1(error) + w_offset L1(offsets) at keypoint cells + w_aux LFA smooth
        L1 (when raw has lfa_points, i.e. from a training-mode forward); the official weights 1, 1, 0.5, 0.2."""
        device = raw["heatmap"].device
        t = {k: v.to(device) for k, v in targets.items()}
        expected = (raw["heatmap"].shape[0], 1, *self.fmap_size)
        if tuple(t["heatmap"].shape) != expected:
            raise ValueError(f"GANetHead.loss: targets['heatmap'] must be {expected}, got {tuple(t['heatmap'].shape)}")
        parts = {
            "heatmap": heatmap_focal_loss(raw["heatmap"], t["heatmap"]),
            "error": masked_l1(raw["error"], t["error"], t["mask"], per_channel=False),
            "offset": masked_l1(raw["offsets"], t["offsets"], t["mask"], per_channel=True),
        }
        if "lfa_points" in raw:
            parts["lfa"] = lfa_loss(raw["lfa_points"], t["lfa_points"], t["lfa_valid"], self.lfa_beta)
        else:
            parts["lfa"] = torch.zeros_like(parts["heatmap"])
        per_sample = sum(self.weights[name] * value for name, value in parts.items())
        return {"loss": per_sample.mean(), "per_sample": per_sample,
                **{f"{name}_loss": value.mean() for name, value in parts.items()}}

    # ------------------------------------------------------------------ decode
    def decode(
        self,
        raw: dict,
        kpt_threshold: float = 0.4,
        root_threshold: float = 1.0,
        cluster_threshold: float = 5.0,
        min_points: int = 11,
        *,
        with_scores: bool = False,
    ) -> list[list[np.ndarray]] | list[list[tuple[np.ndarray, float]]]:
        """Per image: lanes as (N, 2) arrays in input pixels, y descending, left to right (codec.py).
        The defaults are the official CULane ones (stride 8, 320x800): root_threshold in heatmap cells;
        cluster_threshold in heatmap cells at reference_width, scaled to the input width (5 cells = 40 px at
        800 px wide); min_points keypoints per lane (the official "more than 10", for a 40-row heatmap: lower
        it for a smaller input). `with_scores`: (lane, score) pairs, the score the heatmap value of the lane's start
        keypoint (the strongest of the start candidates whose start points made it: codec.decode_lanes); GANet
        gives a lane no score of its own, and that keypoint's value is what its decoding thresholds on."""
        return decode_lanes(raw["heatmap"], raw["offsets"], raw["error"], self.stride, self.image_size,
                            kpt_threshold, root_threshold, cluster_threshold * self.threshold_scale,
                            int(min_points), with_scores=with_scores)
