"""LaneATT head (Tabelini et al., "Keep your Eyes on the Lane", CVPR 2021).

Anchor features are pooled from the last feature map along each line anchor, mixed by the
anchor attention, and classified / regressed (length + x offsets). ``forward`` returns raw
tensors only (ONNX-exportable); NMS and lane assembly live in ``decode``.

Distance thresholds (matching, NMS) are given in pixels at ``reference_width`` (640, the
official input width) and scaled by W / reference_width, so the defaults fit any input size.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from lanevil_train.lanes import row_proposal_to_lane
from lanevil_train.models.head import LaneHead
from lanevil_train.models.laneatt_anchors import (
    TARGET_META,
    anchor_cut_indices,
    encode_lanes,
    generate_anchors,
    row_ys,
)
from lanevil_train.models.losses import anchor_target_distances, focal_loss
from lanevil_train.models.nms import lane_ends, lane_nms


class LaneATTHead(LaneHead):
    """LaneATT: anchor feature pooling, anchor attention, classification and regression.

    It reads the last of the feature maps it is given (the stride-32 stage in its paper)."""

    def __init__(
        self,
        in_channels: list[int],
        in_strides: list[int],
        image_size: tuple[int, int],
        n_offsets: int = 72,
        anchor_feat_channels: int = 64,
        max_lanes: int = 6,
        topk_anchors: int | None = None,
        lateral_n: int | None = None,
        bottom_n: int | None = None,
        anchor_frequency: np.ndarray | None = None,
        pos_threshold: float = 15.0,
        neg_threshold: float = 20.0,
        reference_width: float = 640.0,
        cls_loss_weight: float = 10.0,
        focal_alpha: float = 0.25,
        focal_gamma: float = 2.0,
    ) -> None:
        super().__init__(in_channels, in_strides, image_size)
        h, w = self.image_size
        feature_stride = self.in_strides[-1]
        if neg_threshold < pos_threshold:
            raise ValueError(f"LaneATTHead: neg_threshold {neg_threshold} must be >= pos_threshold {pos_threshold}")
        self.n_offsets = n_offsets
        self.max_lanes = max_lanes
        self.feature_stride = feature_stride
        self.threshold_scale = w / reference_width
        self.pos_threshold = pos_threshold * self.threshold_scale
        self.neg_threshold = neg_threshold * self.threshold_scale
        self.cls_loss_weight = cls_loss_weight
        self.focal_alpha, self.focal_gamma = focal_alpha, focal_gamma

        anchors = generate_anchors(self.image_size, n_offsets, lateral_n, bottom_n)
        if topk_anchors is not None and topk_anchors < len(anchors):
            if anchor_frequency is not None:
                freq = np.asarray(anchor_frequency, dtype=np.float64)
                if freq.shape != (len(anchors),):
                    raise ValueError(f"LaneATTHead: anchor_frequency has shape {freq.shape}, expected ({len(anchors)},)")
                index = np.sort(np.argsort(-freq, kind="stable")[:topk_anchors])
            else:  # no statistics: an even spread over the anchor list
                index = np.unique(np.round(np.linspace(0, len(anchors) - 1, topk_anchors)).astype(np.int64))
            anchors = anchors.subset(index)
        if len(anchors) < 2:
            raise ValueError("LaneATTHead: need at least 2 anchors")
        self.n_anchors = len(anchors)
        cols, valid, (hf, wf) = anchor_cut_indices(anchors, self.image_size, feature_stride)
        self.fmap_size = (hf, wf)
        self.register_buffer("anchor_xs", torch.from_numpy(anchors.xs).float(), persistent=False)
        self.register_buffer("anchor_starts", torch.from_numpy(anchors.starts), persistent=False)
        self.register_buffer("cut_cols", torch.from_numpy(cols), persistent=False)
        self.register_buffer("cut_rows", torch.arange(hf)[None, :].expand(self.n_anchors, hf).contiguous(), persistent=False)
        self.register_buffer("cut_valid", torch.from_numpy(valid), persistent=False)
        self.row_ys = row_ys(h, n_offsets)

        feat_dim = anchor_feat_channels * hf
        self.conv1 = nn.Conv2d(self.in_channels[-1], anchor_feat_channels, kernel_size=1)
        self.attention_layer = nn.Linear(feat_dim, self.n_anchors - 1)
        self.cls_layer = nn.Linear(2 * feat_dim, 2)
        self.reg_layer = nn.Linear(2 * feat_dim, n_offsets + 1)
        for layer in (self.cls_layer, self.reg_layer):
            nn.init.normal_(layer.weight, 0.0, 0.001)
            nn.init.zeros_(layer.bias)

    # ------------------------------------------------------------------ forward
    def forward(self, features: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        """Raw outputs: cls_logits (B, A, 2), length (B, A) in rows, xs (B, A, S) in input pixels."""
        x = self.conv1(features[-1])
        hf, wf = self.fmap_size
        # zero-pad then crop to the expected map size (VGG floors odd sizes where ResNet rounds
        # up); unconditional, so the graph has no shape-dependent branch
        x = F.pad(x, (0, wf, 0, hf))[:, :, :hf, :wf]
        b, c = x.shape[0], x.shape[1]
        feats = x[:, :, self.cut_rows, self.cut_cols] * self.cut_valid  # (B, C, A, Hf)
        feats = feats.permute(0, 2, 1, 3).reshape(b, self.n_anchors, c * hf)
        att = torch.softmax(self.attention_layer(feats), dim=-1)  # (B, A, A-1): weights over the others
        a = self.n_anchors
        # place the (A, A-1) weights off the diagonal of an (A, A) matrix without a scatter
        att = F.pad(att.reshape(b, a - 1, a), (0, 1)).reshape(b, a * a - 1)
        att = F.pad(att, (1, 0)).reshape(b, a, a)
        context = torch.bmm(att, feats)
        joint = torch.cat([context, feats], dim=-1)
        reg = self.reg_layer(joint)
        return {"cls_logits": self.cls_layer(joint), "length": reg[..., 0], "xs": self.anchor_xs + reg[..., 1:]}

    # ------------------------------------------------------------------ targets
    def encode(self, lanes: list[np.ndarray], meta: dict | None = None) -> dict[str, np.ndarray]:
        """GT lanes (input pixels) -> {"lanes": float32 (max_lanes, 3 + n_offsets)}: [valid, start, length, xs]."""
        return {"lanes": encode_lanes(lanes, self.image_size, self.n_offsets, self.max_lanes)}

    def match(self, targets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Anchor assignment: positives (B, A), negatives (B, A), index of the matched target (B, A)."""
        t = targets.to(self.anchor_xs.device).float()
        dist = anchor_target_distances(
            self.anchor_xs, self.anchor_starts, t[..., 0], t[..., 1], t[..., 2], t[..., TARGET_META:]
        )
        best, idx = dist.min(dim=-1)
        return best < self.pos_threshold, best > self.neg_threshold, idx

    def loss(self, raw: dict, targets: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Focal classification + smooth-L1 regression of positives, per image as the official."""
        targets = targets["lanes"].to(raw["xs"].device).float()
        if targets.ndim != 3 or targets.shape[-1] != TARGET_META + self.n_offsets:
            raise ValueError(
                f"LaneATTHead.loss: targets must be (B, max_lanes, {TARGET_META + self.n_offsets}), "
                f"got {tuple(targets.shape)}"
            )
        with torch.no_grad():
            pos, neg, idx = self.match(targets)
            matched = torch.gather(targets, 1, idx[..., None].expand(-1, -1, targets.shape[-1]))  # (B, A, D)
            t_end = matched[..., 1] + matched[..., 2] - 1
            a_start = self.anchor_starts[None, :].float()
            len_target = t_end - a_start + 1
            rows = torch.arange(self.n_offsets, device=targets.device)
            row_ok = (rows >= a_start[..., None]) & (rows <= t_end[..., None])  # (B, A, S)
        n_pos = pos.sum(dim=1).float()
        focal = focal_loss(raw["cls_logits"], pos.long(), self.focal_alpha, self.focal_gamma)
        cls_b = (focal * (pos | neg)).sum(dim=1) / n_pos.clamp(min=1)
        sl1_len = F.smooth_l1_loss(raw["length"], len_target, reduction="none")
        x_target = torch.where(row_ok, matched[..., TARGET_META:], raw["xs"].detach())
        sl1_xs = F.smooth_l1_loss(raw["xs"], x_target, reduction="none").sum(-1)
        reg_sum = ((sl1_len + sl1_xs) * pos).sum(dim=1)
        reg_b = reg_sum / (n_pos * (self.n_offsets + 1)).clamp(min=1)
        per_sample = self.cls_loss_weight * cls_b + reg_b
        return {"loss": per_sample.mean(), "cls_loss": cls_b.mean(), "reg_loss": reg_b.mean(), "per_sample": per_sample}

    # ------------------------------------------------------------------ decode
    def decode(
        self,
        raw: dict,
        conf_threshold: float = 0.5,
        nms_threshold: float = 50.0,
        nms_topk: int | None = None,
    ) -> list[list[np.ndarray]]:
        """Per image: lanes as (N, 2) float arrays in input pixels, y descending, left to right."""
        scores = torch.softmax(raw["cls_logits"].detach().float(), dim=-1)[..., 1]
        lengths = raw["length"].detach().float()
        xs = raw["xs"].detach().float()
        starts = self.anchor_starts.to(xs.device)
        top_k = self.max_lanes if nms_topk is None else nms_topk
        out: list[list[np.ndarray]] = []
        for b in range(scores.shape[0]):
            cand = torch.nonzero(scores[b] > conf_threshold).flatten()
            keep = cand[lane_nms(xs[b, cand], starts[cand], lengths[b, cand], scores[b, cand],
                                 nms_threshold * self.threshold_scale, top_k)]
            ends = lane_ends(starts[keep], lengths[b, keep], self.n_offsets).cpu().numpy()
            lanes = []
            for k, end in zip(keep.cpu().numpy(), ends):
                lane = row_proposal_to_lane(xs[b, k].cpu().numpy().astype(np.float64), self.row_ys, int(starts[k]),
                                            int(end), self.image_size[1])
                if lane is not None:
                    lanes.append(lane)
            lanes.sort(key=lambda ln: ln[0, 0])
            out.append(lanes)
        return out
