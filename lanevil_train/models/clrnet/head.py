"""CLRNet head (Zheng et al., "CLRNet: Cross Layer Refinement Network for Lane Detection", CVPR 2022).

Learnable straight-line priors (start_y, start_x, theta; priors.py) are refined over the FPN levels from
the coarsest to the finest: at each stage, ROIGather samples the stage's feature map along every prior line
(grid_sample at 36 of the 72 rows, laid out top row first as the official), mixes it with the ROI features of
the earlier stages, reduces it with an fc layer and lets it attend to the whole (resized) feature map; shared
fc layers then classify each prior (2 logits) and regress start_y, start_x, theta, the length and 72 x offsets.
A stage's refined line (without the offsets, detached) is the next stage's prior. The loss (loss.py) is computed on
every stage's predictions, with a dynamic assignment of predictions to lanes; NMS lives in ``decode`` only.

The official training's auxiliary segmentation loss is an option (``seg_loss_weight`` > 0; the official
weight is 1.0): a 1x1 convolution (after dropout 0.1) over the refined levels resized to the finest one and
concatenated, upsampled to the input, trained by a cross-entropy with the background weighted 0.4 against
lane masks drawn per lane slot (scnn.codec, as CULane's labels; ``seg_lanes`` slots, max_lanes unless set: the
official TuSimple masks have 6 while it keeps 5 lanes, tools/generate_seg_tusimple.py:45-57 and
configs/clrnet/clr_resnet18_tusimple.py:12, 124). It runs in training only, so decoding and export never see it;
with the weight 0 the decoder is not built.

Distances the official gives in pixels at its 800 px wide input (the Line IoU radius 15, the NMS threshold 50,
the start_x loss) are scaled to the input width by W / reference_width.

The S rows lie from the bottom row to y = 0, ``row_span`` pixels: ``last_pixel`` (the default) puts the bottom row
on the image's last pixel row (y = H-1), ``height`` one pixel below it (y = H), as the official (priors.py), whose
published weights need it (models/clrnet/official.py).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from lanevil_train.lanes import as_lane, row_proposal_to_lane
from lanevil_train.models.clrnet.codec import (
    TARGET_META,
    clrnet_nms,
    encode_lanes,
    official_kept_rows,
    official_rows,
    start_rows,
)
from lanevil_train.models.clrnet.loss import clrnet_losses, segmentation_loss
from lanevil_train.models.clrnet.priors import (
    init_prior_embeddings,
    line_xs,
    row_fractions,
    row_ys,
    sample_indices,
)
from lanevil_train.models.head import LaneHead, lanes_with_scores
from lanevil_train.models.masks import draw_width
from lanevil_train.models.masks import encode_lanes as encode_masks
from lanevil_train.rules import check_settings, integer, null_or, number, one_of

ROW_SPANS = ("last_pixel", "height")  # the bottom row at y = H-1 (ours) or y = H (the official's)
LANE_POINTS = ("inside", "official")  # decode's lane points: this project's, or the official Lane's (decode)


def _conv_bn_relu(c_in: int, c_out: int, kernel, padding) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, kernel, padding=padding, bias=False), nn.BatchNorm2d(c_out),
                         nn.ReLU(inplace=True))


def _fc_stack(dim: int, n: int) -> nn.Sequential:
    return nn.Sequential(*[m for _ in range(n) for m in (nn.Linear(dim, dim), nn.ReLU(inplace=True))])


class ROIGather(nn.Module):
    """The paper's ROIGather: a prior's features from this and the earlier stages (each a (9, 1) conv along the
    sampled points, concatenated, another (9, 1) conv), flattened through an fc layer + LayerNorm, then
    attention of that feature (query) over the whole feature map resized to `attention_size` (keys, values);
    the attended context is added back, as the official (its output weights start at zero)."""

    def __init__(self, channels: int, num_priors: int, sample_points: int, stages: int,
                 attention_size: tuple[int, int], mid_channels: int = 48) -> None:
        super().__init__()
        self.channels, self.num_priors = channels, num_priors
        self.attention_size = tuple(int(v) for v in attention_size)
        self.convs = nn.ModuleList(_conv_bn_relu(channels, mid_channels, (9, 1), (4, 0)) for _ in range(stages))
        self.catconvs = nn.ModuleList(_conv_bn_relu(mid_channels * (i + 1), channels, (9, 1), (4, 0))
                                      for i in range(stages))
        self.fc = nn.Linear(sample_points * channels, channels)
        self.fc_norm = nn.LayerNorm(channels)
        self.f_key = _conv_bn_relu(channels, channels, 1, 0)
        self.f_value = nn.Conv2d(channels, channels, 1)
        # one weight and bias per prior (the official's grouped 1x1 Conv1d over the prior axis)
        self.f_query = nn.Sequential(nn.Conv1d(num_priors, num_priors, 1, groups=num_priors), nn.ReLU())
        self.W = nn.Conv1d(num_priors, num_priors, 1, groups=num_priors)
        nn.init.zeros_(self.W.weight)
        nn.init.zeros_(self.W.bias)

    def transform(self, roi: torch.Tensor, stage: int) -> torch.Tensor:
        """The (9, 1) conv of the ROI features pooled at `stage` (B, C, Ns, P) -> (B, mid, Ns, P). The official
        recomputes it at every later stage; it is the same tensor, so the head keeps it."""
        return self.convs[stage](roi)

    def forward(self, rois: list[torch.Tensor], fmap: torch.Tensor, stage: int) -> torch.Tensor:
        """rois: transform() of the ROI features of stages 0..stage; fmap (B, C, H, W) -> (B, P, C).

        The ROI features are laid out (B, C, Ns, P), the priors as the conv's width (the official's (B*P, C, Ns,
        1) computes the same, with the same batch-norm statistics, about twice as slowly on CPU)."""
        b = fmap.shape[0]
        roi = self.catconvs[stage](torch.cat(rois, dim=1)).permute(0, 3, 1, 2)  # (B, P, C, Ns)
        roi = F.relu(self.fc_norm(self.fc(roi.reshape(b, self.num_priors, -1))))
        key = F.interpolate(self.f_key(fmap), size=self.attention_size).flatten(2)  # (B, C, HW)
        value = F.interpolate(self.f_value(fmap), size=self.attention_size).flatten(2).transpose(1, 2)
        attention = torch.softmax(torch.matmul(self.f_query(roi), key) * self.channels ** -0.5, dim=-1)
        context = self.W(torch.matmul(attention, value))
        return roi + F.dropout(context, p=0.1, training=self.training)


class CLRNetHead(LaneHead):
    """CLRNet: prior refinement over the last `refine_layers` feature maps (an FPN's, coarsest last).

    forward -> {"cls_logits": (B, R, P, 2), "lines": (B, R, P, 4), "xs": (B, R, P, S)} for every refinement
    stage r (the last one is the output): lines are [start_y, start_x, theta, length] in the official's
    normalised units (priors.py; length in rows / (S-1)), xs the x at the S rows in input pixels.
    """

    # lane_points=official: whether the official decoding keeps a kept row's points left of the image (x < 0):
    # CLRNet's drops them (codec.official_kept_rows), CLRerNet's keeps every row from the start to the end
    OFFICIAL_KEEPS_LEFT = False

    # The constructor's parameters with a range, and what a good value of each is: checked by the constructor,
    # and by the config check under model.head.* before any work (one place to say it).
    SETTINGS = {
        "num_points": integer(2),
        "num_priors": integer(1),
        "refine_layers": integer(1),
        "sample_points": integer(2),
        "fc_hidden_dim": integer(1),
        "num_fc": integer(0),
        "max_lanes": integer(1),
        "reference_width": number(0, low_open=True),
        "iou_radius": number(0, low_open=True),
        "cls_loss_weight": number(0),
        "xyt_loss_weight": number(0),
        "iou_loss_weight": number(0),
        "focal_alpha": number(0, 1),
        "focal_gamma": number(0),
        "seg_loss_weight": number(0),  # 0: no auxiliary segmentation
        "seg_background_weight": number(0, low_open=True),
        "seg_lane_width": number(0, low_open=True),
        "seg_reference_width": number(0, low_open=True),
        "seg_lanes": null_or(integer(1)),  # null: max_lanes
        "row_span": one_of(*ROW_SPANS),
    }

    def __init__(self, in_channels: list[int], in_strides: list[int], image_size: tuple[int, int],
                 num_points: int = 72, num_priors: int = 192, refine_layers: int = 3, sample_points: int = 36,
                 fc_hidden_dim: int = 64, num_fc: int = 2, max_lanes: int = 4, reference_width: float = 800.0,
                 iou_radius: float = 15.0, cls_loss_weight: float = 2.0, xyt_loss_weight: float = 0.2,
                 iou_loss_weight: float = 2.0, focal_alpha: float = 0.25, focal_gamma: float = 2.0,
                 seg_loss_weight: float = 0.0, seg_background_weight: float = 0.4, seg_lane_width: float = 16.0,
                 seg_reference_width: float = 1640.0, seg_lanes: int | None = None,
                 row_span: str = "last_pixel") -> None:
        check_settings(self.SETTINGS, locals(), "model.head")
        super().__init__(in_channels, in_strides, image_size)
        h, w = self.image_size
        if refine_layers < 1 or refine_layers > len(self.in_channels):
            raise ValueError(f"CLRNetHead: refine_layers={refine_layers} needs that many feature maps (1 to "
                             f"{len(self.in_channels)} given: in_strides {self.in_strides})")
        channels = self.in_channels[-refine_layers:]
        if any(c != fc_hidden_dim for c in channels):
            raise ValueError(f"CLRNetHead: in_channels {channels} of the refined levels must all equal "
                             f"fc_hidden_dim={fc_hidden_dim} (ROIGather attends with the ROI feature over the map "
                             f"channels): give the model an FPN neck with out_channels={fc_hidden_dim}")
        self.n_points, self.n_strips = num_points, num_points - 1
        self.num_priors, self.refine_layers, self.max_lanes = num_priors, refine_layers, max_lanes
        self.width_scale = w / reference_width
        self.iou_radius = iou_radius * self.width_scale
        self.weights = {"cls": cls_loss_weight, "xytl": xyt_loss_weight, "iou": iou_loss_weight}
        self.focal_alpha, self.focal_gamma = focal_alpha, focal_gamma
        self.seg_loss_weight, self.seg_background_weight = float(seg_loss_weight), float(seg_background_weight)
        self.seg_line_width = draw_width(seg_lane_width, seg_reference_width, w)  # drawn mask width, input px
        self.seg_lanes = max_lanes if seg_lanes is None else int(seg_lanes)  # lane slots of the masks
        self.row_span = float(h - 1 if row_span == "last_pixel" else h)  # pixels from the bottom row to the top one
        self.row_ys = row_ys(h, num_points, self.row_span).double().numpy()
        # the official decoding's row heights (fractions of H, bottom first): its float32 prior_ys, read in double
        self.official_row_heights = torch.linspace(1.0, 0.0, num_points, dtype=torch.float32).double().numpy()

        self.prior_embeddings = nn.Parameter(init_prior_embeddings(num_priors))  # validates num_priors
        self.register_buffer("fractions", row_fractions(num_points), persistent=False)
        self.register_buffer("sample_index", sample_indices(num_points, sample_points), persistent=False)
        # grid_sample's y in [-1, 1] (top to bottom) of the sampled rows
        self.register_buffer("sample_grid_y", 1.0 - 2.0 * self.fractions[self.sample_index], persistent=False)
        coarsest = max(self.in_strides[-refine_layers:])
        attention_size = (math.ceil(h / coarsest), math.ceil(w / coarsest))  # (10, 25) at 320x800, as the official
        self.roi_gather = ROIGather(fc_hidden_dim, num_priors, sample_points, refine_layers, attention_size)
        self.cls_fc = _fc_stack(fc_hidden_dim, num_fc)
        self.reg_fc = _fc_stack(fc_hidden_dim, num_fc)
        self.cls_layer = nn.Linear(fc_hidden_dim, 2)
        self.reg_layer = nn.Linear(fc_hidden_dim, 4 + num_points)  # start_y, start_x, theta, length, offsets
        for layer in (self.cls_layer, self.reg_layer):
            nn.init.normal_(layer.weight, 0.0, 1e-3)
            nn.init.normal_(layer.bias, 0.0, 1e-3)
        # the official SegDecoder: background + one class per lane slot, over the refined levels concatenated
        self.seg_decoder = None
        if self.seg_loss_weight > 0:
            self.seg_decoder = nn.Sequential(nn.Dropout2d(0.1),
                                             nn.Conv2d(fc_hidden_dim * refine_layers, self.seg_lanes + 1, 1))

    # ------------------------------------------------------------------ forward
    def _pool(self, fmap: torch.Tensor, xs: torch.Tensor) -> torch.Tensor:
        """Features of fmap (B, C, H, W) along each line: xs (B, P, S) as fractions of W-1 -> (B, C, Ns, P)."""
        gx = xs[..., self.sample_index] * 2.0 - 1.0
        grid = torch.stack([gx, self.sample_grid_y.expand_as(gx)], dim=-1).to(fmap.dtype)  # (B, P, Ns, 2)
        return F.grid_sample(fmap, grid, align_corners=True).transpose(2, 3)  # (B, C, P, Ns) -> (B, C, Ns, P)

    def forward(self, features: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        levels = list(features[-self.refine_layers:])[::-1]  # coarsest first
        b = levels[0].shape[0]
        w = self.image_size[1]
        lines = self.prior_embeddings[None].expand(b, -1, -1)  # (B, P, 3), learnt through stage 0
        xs = line_xs(lines, self.fractions, self.image_size, self.row_span)
        rois, out_cls, out_lines, out_xs = [], [], [], []
        for stage, fmap in enumerate(levels):
            rois.append(self.roi_gather.transform(self._pool(fmap, xs), stage))
            feat = self.roi_gather(rois, fmap, stage)  # (B, P, C)
            cls = self.cls_layer(self.cls_fc(feat))
            reg = self.reg_layer(self.reg_fc(feat))
            refined = lines + reg[..., :3]
            line = line_xs(refined, self.fractions, self.image_size, self.row_span)
            out_cls.append(cls)
            out_lines.append(torch.cat([refined, reg[..., 3:4]], dim=-1))
            out_xs.append((line + reg[..., 4:]) * (w - 1))
            lines, xs = refined.detach(), line.detach()  # the next stage's priors
        out = {"cls_logits": torch.stack(out_cls, 1), "lines": torch.stack(out_lines, 1),
               "xs": torch.stack(out_xs, 1)}
        if self.training and self.seg_decoder is not None:
            out["seg"] = self._segment(levels)
        return out

    def _segment(self, levels: list[torch.Tensor]) -> torch.Tensor:
        """The auxiliary segmentation logits (B, seg_lanes + 1, H, W): the levels (coarsest first) resized to the
        finest one's size, concatenated in that order, through the decoder, upsampled to the input size."""
        size = levels[-1].shape[-2:]
        stacked = torch.cat([F.interpolate(f, size=size, mode="bilinear", align_corners=False) for f in levels], 1)
        return F.interpolate(self.seg_decoder(stacked), size=self.image_size, mode="bilinear", align_corners=False)

    # ------------------------------------------------------------------ targets
    def encode(self, lanes: list[np.ndarray], meta: dict | None = None) -> dict[str, np.ndarray]:
        """GT lanes (input pixels) -> {"lanes": float32 (max_lanes, 5 + S)} [valid, start_y, start_x, theta,
        length, xs] (codec.py); with the auxiliary segmentation also "seg": uint8 (H, W), 0 background and
        1 + slot on each lane's drawn line (slots as CULane's labels: scnn.codec, "ego")."""
        out = {"lanes": encode_lanes(lanes, self.image_size, self.n_points, self.max_lanes, self.row_span)}
        if self.seg_decoder is not None:
            out["seg"] = encode_masks(lanes, self.image_size, self.seg_lanes, self.seg_line_width)["seg"]
        return out

    def loss(self, raw: dict, targets: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """The official loss on every stage's predictions, averaged over the stages: w_cls focal + w_xyt
        smooth-L1 of (start_y, start_x, theta, length) + w_iou (1 - Line IoU); plus, in training with the
        auxiliary segmentation, w_seg x its cross-entropy (once, not per stage, as the official); parts logged
        unweighted."""
        xs = raw["xs"]
        b, r, p, s = xs.shape
        t = targets["lanes"].to(xs.device).float()
        if t.ndim != 3 or t.shape[0] != b or t.shape[-1] != TARGET_META + s:
            raise ValueError(f"CLRNetHead.loss: targets['lanes'] must be ({b}, max_lanes, {TARGET_META + s}), "
                             f"got {tuple(t.shape)}")
        t = t[:, None].expand(b, r, *t.shape[1:]).reshape(b * r, *t.shape[1:])
        parts = self._stage_losses(raw["cls_logits"].reshape(b * r, p, 2), raw["lines"].reshape(b * r, p, 4),
                                   xs.reshape(b * r, p, s), t)
        per_stage = {k: parts[k].reshape(b, r).mean(1) for k in self.weights}  # (B,) each, over the stages
        per_sample = sum(self.weights[k] * v for k, v in per_stage.items())
        out = {"cls_loss": per_stage["cls"].mean(), "xytl_loss": per_stage["xytl"].mean(),
               "iou_loss": per_stage["iou"].mean()}
        if "seg" in raw and self.seg_loss_weight > 0:  # training outputs only (forward in train mode)
            if "seg" not in targets:
                raise ValueError("CLRNetHead.loss: the auxiliary segmentation (model.head.seg_loss_weight > 0) needs "
                                 "targets['seg'] from this head's encode")
            seg = segmentation_loss(raw["seg"], targets["seg"].to(xs.device), self.seg_background_weight)
            per_sample = per_sample + self.seg_loss_weight * seg
            out["seg_loss"] = seg.mean()
        return {"loss": per_sample.mean(), "per_sample": per_sample, **out}

    def _stage_losses(self, cls_logits: torch.Tensor, lines: torch.Tensor, xs: torch.Tensor,
                      targets: torch.Tensor) -> dict[str, torch.Tensor]:
        """The loss terms (N,) of a flat batch of N (image, stage) predictions: CLRNet's assignment and Line IoU
        (loss.clrnet_losses); CLRerNet swaps both for its LaneIoU."""
        return clrnet_losses(cls_logits, lines, xs, targets, self.image_size, self.iou_radius, 1.0 / self.width_scale,
                             self.focal_alpha, self.focal_gamma, meta=TARGET_META)

    # ------------------------------------------------------------------ decode
    def decode(self, raw: dict, conf_threshold: float = 0.4, nms_threshold: float = 50.0,
               nms_topk: int | None = None, lane_points: str = "inside", *,
               with_scores: bool = False) -> list[list[np.ndarray]] | list[list[tuple[np.ndarray, float]]]:
        """Per image: the last stage's lanes scoring at least conf_threshold, after NMS (nms_threshold: mean x
        distance in pixels at reference_width; at most nms_topk, default max_lanes), in input pixels, y
        descending, left to right.

        `lane_points` (LANE_POINTS): which points a lane is given. ``inside`` (this project's): its rows inside the
        image plus the exact border crossings, x in input pixels (the network's x x (W-1)). ``official``: the points
        of the official ``Lane`` (models/clrnet/official.py, "Decoding"): every row from its start to its end with
        x >= 0 (past the right edge too), the rows below its start while inside the image, no border points; x at
        the official writers' scale (the network's fraction of W-1 read as a fraction of W) and the rows at the
        official's heights, so that LaneDetector.decode_lanes maps them to the original pixels the official writes.

        `with_scores`: (lane, score) pairs, the score the kept prior's softmax class score at the last refinement
        stage (the one conf_threshold and the NMS read).
        """
        if lane_points not in LANE_POINTS:
            raise ValueError(f"model.decode.lane_points={lane_points!r}: expected one of {', '.join(LANE_POINTS)}")
        scores = torch.softmax(raw["cls_logits"][:, -1].detach().float(), dim=-1)[..., 1]
        lines = raw["lines"][:, -1].detach().float()
        xs = raw["xs"][:, -1].detach().float()
        top_k = self.max_lanes if nms_topk is None else nms_topk
        out = []
        for i in range(scores.shape[0]):
            cand = torch.nonzero(scores[i] >= conf_threshold).flatten()
            keep = cand[clrnet_nms(xs[i, cand], lines[i, cand, 0], lines[i, cand, 3], scores[i, cand],
                                   nms_threshold * self.width_scale, top_k, self.n_strips)]
            if lane_points == "official":
                kept = self._official_lanes(xs[i, keep], lines[i, keep])
            else:
                kept = self._inside_lanes(xs[i, keep], lines[i, keep])
            kept_scores = scores[i, keep].cpu().numpy()
            out.append(lanes_with_scores([lane for _, lane in kept], [kept_scores[k] for k, _ in kept], with_scores))
        return out

    def _inside_lanes(self, xs: torch.Tensor, lines: torch.Tensor) -> list[tuple[int, np.ndarray]]:
        """This project's lanes of the kept predictions (xs (K, S) input pixels, lines (K, 4)): the rows inside
        the image from the start row (extended down while inside) to the end, plus the border crossings; each as
        (its prediction's index in the K, lane)."""
        starts = start_rows(lines[:, 0], self.n_strips).cpu().numpy()
        lengths = torch.floor(lines[:, 3] * self.n_strips + 0.5).long().cpu().numpy()
        w = self.image_size[1]
        lanes = []
        for k, (start, length) in enumerate(zip(starts, lengths)):
            end = min(int(start + length - 1), self.n_strips)
            lane = row_proposal_to_lane(xs[k].cpu().numpy().astype(np.float64), self.row_ys, int(start), end, w)
            if lane is not None:
                lanes.append((k, lane))
        return lanes

    def _official_lanes(self, xs: torch.Tensor, lines: torch.Tensor) -> list[tuple[int, np.ndarray]]:
        """The official Lane's points of the kept predictions (xs (K, S) input pixels, lines (K, 4)), in the input
        pixels that map to the official writers' original pixels: x = fraction x W, y = the official row height x H;
        lanes of fewer than two points dropped (as the official); each as (its prediction's index in the K, lane)."""
        h, w = self.image_size
        fractions = (xs / (w - 1)).cpu().numpy()  # float32: the official's normalised x, as its forward keeps it
        ys = self.official_row_heights * h
        lanes = []
        for k in range(len(fractions)):
            start, end = official_rows(float(lines[k, 0]), float(lines[k, 3]), self.n_strips)
            kept = official_kept_rows(fractions[k], start, end, keep_left=self.OFFICIAL_KEEPS_LEFT)
            if kept.sum() >= 2:
                lanes.append((k, as_lane(np.stack([fractions[k][kept].astype(np.float64) * w, ys[kept]], axis=1))))
        return lanes
