"""GANet head (Wang et al., "A Keypoint-based Global Association Network for Lane Detection", CVPR 2022).

Lanes as keypoints: on the finest FPN level (stride 8 in the paper) a keypoint heatmap (1 channel, sigmoid), the
sub-cell error of each keypoint (2 channels) and, the paper's global association, every keypoint's offset to its
lane's start point (2 channels); decoding groups the keypoints by the start points they point at
(ganet_codec). The Lane-aware Feature Aggregator (LFA) feeds the heatmap branch: at each location it predicts
K points (offsets in feature cells), reads the features there and aggregates them (the official's deformable
1-D convolution: sum_k W_k f(p_k)); an auxiliary loss pulls the K points onto the ground-truth lane. As the
official (``dcn_only_cls``), the offset and error branches read the features without the LFA.

Where this differs from the official, and why:
- the self-attention the official puts on the backbone's last stage before its FPN (two attention layers with a
  sine position embedding, replacing C5) lives here, with the shared FPN neck, on the FPN's coarsest output: one
  attention layer (conv, query/key/value, a zero-initialised residual weight, conv; no position embedding) whose
  output is upsampled and added to the finest level (``top_attention``; the official's top-down path does that
  addition in its FPN);
- the LFA's deformable convolution is grid_sample (models/sampling) at the predicted points of a 1x1 projection
  per point, summed: the same function (sampling is linear), exportable to ONNX;
- per-image loss normalisation (ganet_loss) and the decoding's nearest-centre assignment (ganet_codec).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from lanevil_train.models.ganet_codec import decode_lanes, encode_targets, heatmap_size
from lanevil_train.models.ganet_loss import heatmap_focal_loss, lfa_loss, masked_l1
from lanevil_train.models.head import LaneHead
from lanevil_train.models.sampling import sample_at

HEATMAP_BIAS = -2.19  # CenterNet's initial heatmap bias (sigmoid 0.1)


def _conv_relu(c_in: int, c_out: int, n: int) -> nn.Sequential:
    return nn.Sequential(*[m for i in range(n) for m in (nn.Conv2d(c_in if i == 0 else c_out, c_out, 3, padding=1),
                                                         nn.ReLU(inplace=True))])


def _branch(c_in: int, hidden: int, out: int) -> nn.Sequential:
    """The official CtnetHead branch: 3x3 conv, ReLU, 1x1 conv."""
    return nn.Sequential(nn.Conv2d(c_in, hidden, 3, padding=1), nn.ReLU(inplace=True), nn.Conv2d(hidden, out, 1))


class SelfAttention(nn.Module):
    """The official AttentionLayer: conv-BN-ReLU, attention of every position over all (query/key at C / ratio
    channels), gamma * attended + input (gamma starts at 0), conv-BN-ReLU."""

    def __init__(self, c_in: int, c_out: int, ratio: int = 4) -> None:
        super().__init__()
        self.pre = nn.Sequential(nn.Conv2d(c_in, c_out, 3, padding=1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU())
        self.query = nn.Conv2d(c_out, c_out // ratio, 1)
        self.key = nn.Conv2d(c_out, c_out // ratio, 1)
        self.value = nn.Conv2d(c_out, c_out, 1)
        self.gamma = nn.Parameter(torch.zeros(1))
        self.post = nn.Sequential(nn.Conv2d(c_out, c_out, 3, padding=1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.pre(x)
        b, c, h, w = x.shape
        q = self.query(x).flatten(2).transpose(1, 2)  # (B, N, C')
        k = self.key(x).flatten(2)  # (B, C', N)
        attn = torch.softmax(torch.bmm(q, k), dim=-1)  # (B, N, N): each query over the keys
        out = torch.bmm(self.value(x).flatten(2), attn.transpose(1, 2)).reshape(b, c, h, w)
        return self.post(self.gamma * out + x)


class LaneAwareAggregator(nn.Module):
    """The LFA (the official LanePointsConv): a point branch (convs, 3x3 conv, ReLU, 1x1 conv) predicts K points
    per location as (dx, dy) offsets in feature cells from it; a feature branch (convs) is read at those points
    and aggregated, sum_k W_k f(p_k) + b, then ReLU. The points used for sampling pass only gradient_mul of their
    gradient (the official 0.1); the auxiliary loss acts on the points themselves."""

    def __init__(self, channels: int, feat_channels: int, num_points: int, stacked_convs: int,
                 gradient_mul: float) -> None:
        super().__init__()
        self.num_points = num_points
        self.gradient_mul = gradient_mul
        self.feat_convs = _conv_relu(channels, feat_channels, stacked_convs)
        self.point_convs = _conv_relu(channels, feat_channels, stacked_convs)
        self.point_out = nn.Sequential(nn.Conv2d(feat_channels, channels, 3, padding=1), nn.ReLU(inplace=True),
                                       nn.Conv2d(channels, 2 * num_points, 1))
        # W_k for every point k at once: sampling commutes with a 1x1 conv, so project first, then sample
        self.project = nn.Conv2d(feat_channels, num_points * channels, 1, bias=False)
        self.bias = nn.Parameter(torch.zeros(channels))
        nn.init.normal_(self.point_out[-1].weight, std=0.01)
        nn.init.zeros_(self.point_out[-1].bias)

    @staticmethod
    def sample(fmap: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """fmap (B, C, h, w) read at K points per location, points (B, 2K, h, w) offsets (dx, dy) in cells ->
        (B, C, K, h, w); zero offsets read the location itself, points off the map read zeros."""
        b, k2, h, w = points.shape
        pts = points.reshape(b, k2 // 2, 2, h, w)
        xs = pts[:, :, 0] + torch.arange(w, device=points.device, dtype=points.dtype)
        ys = pts[:, :, 1] + torch.arange(h, device=points.device, dtype=points.dtype)[:, None]
        return sample_at(fmap, xs, ys, (h, w))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Aggregated features (B, C, h, w) and the predicted points (B, 2K, h, w)."""
        points = self.point_out(self.point_convs(x))
        used = (1 - self.gradient_mul) * points.detach() + self.gradient_mul * points
        proj = self.project(self.feat_convs(x))  # (B, K * C, h, w)
        b, _, h, w = proj.shape
        k, c = self.num_points, proj.shape[1] // self.num_points
        sampled = self.sample(proj.reshape(b * k, c, h, w), used.reshape(b * k, 2, h, w))  # (B*K, C, 1, h, w)
        out = sampled.reshape(b, k, c, h, w).sum(1) + self.bias[:, None, None]
        return F.relu(out), points


class GANetHead(LaneHead):
    """GANet on the first (finest) of the feature maps it is given (the stride-8 FPN level in the paper); the
    coarsest one feeds the top self-attention."""

    def __init__(
        self,
        in_channels: list[int],
        in_strides: list[int],
        image_size: tuple[int, int],
        max_lanes: int = 4,
        head_channels: int = 64,
        lfa_channels: int = 256,
        lfa_convs: int = 3,
        lfa_points: int = 7,
        lfa_gradient_mul: float = 0.1,
        lfa_gt_points: int = 41,
        points_per_lane: int = 45,
        radius: int = 2,
        top_attention: bool = True,
        attention_ratio: int = 4,
        heatmap_loss_weight: float = 1.0,
        error_loss_weight: float = 1.0,
        offset_loss_weight: float = 0.5,
        lfa_loss_weight: float = 0.2,
        lfa_beta: float = 1.0 / 9.0,
        reference_width: float = 800.0,
    ) -> None:
        super().__init__(in_channels, in_strides, image_size)
        for name, value, low in (("max_lanes", max_lanes, 1), ("head_channels", head_channels, 1),
                                 ("lfa_channels", lfa_channels, 1), ("lfa_convs", lfa_convs, 0),
                                 ("lfa_points", lfa_points, 1), ("points_per_lane", points_per_lane, 2),
                                 ("radius", radius, 0), ("attention_ratio", attention_ratio, 1)):
            if int(value) != value or value < low:
                raise ValueError(f"GANetHead: {name} must be an integer >= {low}, got {value!r}")
        if lfa_gt_points < lfa_points:
            raise ValueError(f"GANetHead: lfa_gt_points ({lfa_gt_points}) must be >= lfa_points ({lfa_points}): "
                             f"each predicted point is matched to its own lane point")
        if not 0.0 <= lfa_gradient_mul <= 1.0:
            raise ValueError(f"GANetHead: lfa_gradient_mul must be in [0, 1], got {lfa_gradient_mul}")
        if reference_width <= 0:
            raise ValueError(f"GANetHead: reference_width must be > 0, got {reference_width}")
        if lfa_beta <= 0:
            raise ValueError(f"GANetHead: lfa_beta must be > 0, got {lfa_beta}")
        weights = {"heatmap_loss_weight": heatmap_loss_weight, "error_loss_weight": error_loss_weight,
                   "offset_loss_weight": offset_loss_weight, "lfa_loss_weight": lfa_loss_weight}
        for name, value in weights.items():
            if value < 0:
                raise ValueError(f"GANetHead: {name} must be >= 0, got {value}")
        channels = self.in_channels[0]
        if top_attention and channels // attention_ratio < 1:
            raise ValueError(f"GANetHead: attention_ratio {attention_ratio} leaves no query channels of {channels}")
        self.max_lanes = int(max_lanes)
        self.stride = self.in_strides[0]
        self.fmap_size = heatmap_size(self.image_size, self.stride)
        self.points_per_lane, self.radius, self.lfa_gt_points = int(points_per_lane), int(radius), int(lfa_gt_points)
        self.lfa_beta = float(lfa_beta)
        self.threshold_scale = self.image_size[1] / float(reference_width)
        self.weights = {k.removesuffix("_loss_weight"): float(v) for k, v in weights.items()}
        self.attention = SelfAttention(self.in_channels[-1], channels, attention_ratio) if top_attention else None
        self.lfa = LaneAwareAggregator(channels, lfa_channels, lfa_points, lfa_convs, lfa_gradient_mul)
        self.heatmap_head = _branch(channels, head_channels, 1)
        self.offset_head = _branch(channels, head_channels, 2)
        self.error_head = _branch(channels, head_channels, 2)
        nn.init.constant_(self.heatmap_head[-1].bias, HEATMAP_BIAS)
        for branch in (self.offset_head, self.error_head):
            nn.init.zeros_(branch[-1].bias)

    # ------------------------------------------------------------------ forward
    def forward(self, features: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        """heatmap (B, 1, h, w) in [0, 1]; offsets (B, 2, h, w) to the start point and error (B, 2, h, w), in
        heatmap cells (x, y); in training also lfa_points (B, 2K, h, w), the LFA's point offsets."""
        hf, wf = self.fmap_size
        # zero-pad then crop to the expected size (a backbone that floors odd sizes); no shape-dependent branch
        x = F.pad(features[0], (0, wf, 0, hf))[:, :, :hf, :wf]
        if self.attention is not None:
            x = x + F.interpolate(self.attention(features[-1]), size=(hf, wf), mode="nearest")
        aggregated, points = self.lfa(x)
        raw = {"heatmap": torch.sigmoid(self.heatmap_head(aggregated)), "offsets": self.offset_head(x),
               "error": self.error_head(x)}
        if self.training:
            raw["lfa_points"] = points
        return raw

    # ------------------------------------------------------------------ targets
    def encode(self, lanes: list[np.ndarray], meta: dict | None = None) -> dict[str, np.ndarray]:
        """GT lanes (input pixels) -> heatmap, error, offsets, mask, lfa_points, lfa_valid (ganet_codec)."""
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
    ) -> list[list[np.ndarray]]:
        """Per image: lanes as (N, 2) arrays in input pixels, y descending, left to right (ganet_codec).
        The defaults are the official CULane ones (stride 8, 320x800): root_threshold in heatmap cells;
        cluster_threshold in heatmap cells at reference_width, scaled to the input width (5 cells = 40 px at
        800 px wide); min_points keypoints per lane (the official "more than 10", for a 40-row heatmap: lower
        it for a smaller input)."""
        return decode_lanes(raw["heatmap"], raw["offsets"], raw["error"], self.stride, self.image_size,
                            kpt_threshold, root_threshold, cluster_threshold * self.threshold_scale,
                            int(min_points))
