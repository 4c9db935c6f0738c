"""SCNN head (Pan et al., "Spatial As Deep: Spatial CNN for Traffic Scene Understanding", AAAI 2018).

The paper's network is DeepLab-LargeFOV's VGG-16 (pool4 and pool5 removed, conv5 dilated by 2, stride 8:
``model.output_stride: 8``), then this head: a 3x3 convolution dilated by 4 to 1024 channels + BN + ReLU, a
1x1 convolution to 128 channels + BN + ReLU, the spatial message passing (SCNN_D, SCNN_U, SCNN_R, SCNN_L),
dropout 0.1 and a 1x1 convolution to background + one class per lane slot, upsampled bilinearly by the
stride to the input size. The lane-existence branch reads the softmax of the stride-8 class logits,
average-pools it 2x2 and maps it through FC -> 128 -> ReLU -> FC -> max_lanes -> sigmoid (4500 inputs at
288x800 on CULane, as the official model). Loss: per-pixel cross-entropy with the background weighted 0.4,
plus 0.1 x the binary cross-entropy of the existence (the official training). Two choices: the weighted
mean is taken per image (the official one pools the batch), so ``per_sample`` is each image's own loss and
``loss`` their mean; the BCE is computed from the logits (the same value as sigmoid + BCE, stable in fp16).

Message passing (pytorch-auto-drive's SpatialConv): the map is cut into slices (rows for SCNN_D / SCNN_U,
columns for SCNN_R / SCNN_L); in each direction, slice by slice in order, a slice adds ReLU(conv(previous
slice, already updated)), the convolution a C x C kernel of width 9 across the slice, with a bias, so
information travels the whole map in four sequential passes. As the official, the up and left passes stop one
slice short: they start from the last row / column and update down to the second one, leaving row 0 and
column 0 as the down and right passes left them. The feature map is cropped (after a 1-cell zero pad: VGG
floors odd sizes where ResNets round up) to the size fixed by ``image_size`` and the stride, so the loops
have static bounds that tracing and ONNX export unroll (35 + 34 + 99 + 98 slice steps at 288x800).

Targets, slots and post-processing: see ``models/scnn/codec.py``.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from lanevil_train.lanes import SLOT_ASSIGNMENTS, as_lane
from lanevil_train.models.head import LaneHead
from lanevil_train.models.masks import draw_width, encode_lanes
from lanevil_train.models.nms import prune_lanes
from lanevil_train.models.scnn.codec import OFFICIAL_WRITERS, box_blur, lane_points, official_lane_points
from lanevil_train.rules import boolean, check_settings, integer, number, one_of


class SpatialMessagePassing(nn.Module):
    """SCNN's sequential slice-by-slice convolutions, in the order down, up, right, left.

    ``conv_d`` / ``conv_u`` are (1 x k) convolutions applied to a row (1 x W slice), ``conv_r`` / ``conv_l``
    (k x 1) ones applied to a column, each with a bias (torch's default init). Weights start uniform in +-sqrt(2 /
    (k C 5)), the official's: MSRA's variance over 5 (the SCNN author's advice for stable sums over 36 or 100
    slices), as a uniform bound."""

    def __init__(self, channels: int, kernel_size: int = 9) -> None:
        super().__init__()
        if kernel_size < 1 or kernel_size % 2 == 0:
            raise ValueError(f"SpatialMessagePassing: kernel_size must be a positive odd number, got {kernel_size}")
        k, pad = kernel_size, kernel_size // 2
        self.conv_d = nn.Conv2d(channels, channels, (1, k), padding=(0, pad))
        self.conv_u = nn.Conv2d(channels, channels, (1, k), padding=(0, pad))
        self.conv_r = nn.Conv2d(channels, channels, (k, 1), padding=(pad, 0))
        self.conv_l = nn.Conv2d(channels, channels, (k, 1), padding=(pad, 0))
        bound = math.sqrt(2.0 / (k * channels * 5))
        for conv in (self.conv_d, self.conv_u, self.conv_r, self.conv_l):
            nn.init.uniform_(conv.weight, -bound, bound)

    @staticmethod
    def _pass(slices: list[torch.Tensor], conv: nn.Module, reverse: bool) -> list[torch.Tensor]:
        """One direction: slice i += relu(conv(slice i-1, already updated)) in pass order, the pass's first slice
        unchanged; a reverse (up, left) pass also leaves its last one, slice 0 of the map, unchanged (the
        official's loops ``range(H - 2, 0, -1)``)."""
        out = list(slices[::-1] if reverse else slices)
        for i in range(1, len(out) - 1 if reverse else len(out)):
            out[i] = out[i] + F.relu(conv(out[i - 1]))
        return out[::-1] if reverse else out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        rows = list(x.split(1, dim=2))
        rows = self._pass(self._pass(rows, self.conv_d, reverse=False), self.conv_u, reverse=True)
        cols = list(torch.cat(rows, dim=2).split(1, dim=3))
        cols = self._pass(self._pass(cols, self.conv_r, reverse=False), self.conv_l, reverse=True)
        return torch.cat(cols, dim=3)


class SCNNHead(LaneHead):
    """SCNN: per-pixel lane classes (background + max_lanes slots) and per-slot lane existence.

    Reads the last feature map it is given (stride 8 in the paper). ``hidden_channels`` is the dilated 3x3
    convolution's width (1024 in the paper), ``mp_channels`` the message-passing width (128), ``mp_kernel``
    its kernel width (9). ``lane_width`` px at ``reference_width`` is the drawn label width (CULane: 16 px
    at 1640); ``slot_assignment`` "ego" or "packed" (see models/scnn/codec.py). ``align_corners`` is the bilinear
    upsampling's to the input size: false by default, true for pytorch-auto-drive's published weights (its
    inference upsamples so, utils/lane_det_utils.py l. 100)."""

    # The constructor's parameters with a range, and what a good value of each is: checked by the constructor,
    # and by the config check under model.head.* before any work (one place to say it).
    SETTINGS = {
        "max_lanes": integer(1),
        "hidden_channels": integer(1),
        "dilation": integer(1),
        "mp_channels": integer(1),
        "mp_kernel": integer(1),
        "dropout": number(0, 1, high_open=True),
        "exist_hidden": integer(1),
        "background_weight": number(0, low_open=True),
        "exist_loss_weight": number(0),
        "lane_width": number(0, low_open=True),
        "reference_width": number(0, low_open=True),
        "slot_assignment": one_of(*SLOT_ASSIGNMENTS),
        "align_corners": boolean(),
    }

    def __init__(
        self,
        in_channels: list[int],
        in_strides: list[int],
        image_size: tuple[int, int],
        max_lanes: int = 4,
        hidden_channels: int = 1024,
        dilation: int = 4,
        mp_channels: int = 128,
        mp_kernel: int = 9,
        dropout: float = 0.1,
        exist_hidden: int = 128,
        background_weight: float = 0.4,
        exist_loss_weight: float = 0.1,
        lane_width: float = 16.0,
        reference_width: float = 1640.0,
        slot_assignment: str = "ego",
        align_corners: bool = False,
    ) -> None:
        check_settings(self.SETTINGS, locals(), "model.head")
        super().__init__(in_channels, in_strides, image_size)
        h, w = self.image_size
        if mp_kernel % 2 == 0:
            raise ValueError(f"model.head.mp_kernel: expected an odd integer, got {mp_kernel}")
        stride = self.in_strides[-1]
        hf, wf = math.ceil(h / stride), math.ceil(w / stride)
        if hf < 2 or wf < 2:
            raise ValueError(f"SCNNHead: image_size {self.image_size} gives a {hf}x{wf} map at stride {stride}; the "
                             f"existence branch's 2x2 pooling needs at least 2x2")
        self.max_lanes = int(max_lanes)
        self.num_classes = self.max_lanes + 1
        self.feature_stride = stride
        self.fmap_size = (hf, wf)
        self.background_weight = float(background_weight)
        self.exist_loss_weight = float(exist_loss_weight)
        self.slot_assignment = slot_assignment
        self.align_corners = bool(align_corners)
        self.line_width = draw_width(lane_width, reference_width, w)  # drawn label width, input px

        self.reduce = nn.Sequential(
            nn.Conv2d(self.in_channels[-1], hidden_channels, 3, padding=dilation, dilation=dilation, bias=False),
            nn.BatchNorm2d(hidden_channels),
            nn.ReLU(inplace=True),
            nn.Conv2d(hidden_channels, mp_channels, 1, bias=False),
            nn.BatchNorm2d(mp_channels),
            nn.ReLU(inplace=True),
        )
        self.message_passing = SpatialMessagePassing(mp_channels, mp_kernel)
        self.dropout = nn.Dropout2d(dropout)
        self.classifier = nn.Conv2d(mp_channels, self.num_classes, 1)
        self.exist_fc = nn.Sequential(
            nn.Linear(self.num_classes * (hf // 2) * (wf // 2), exist_hidden),
            nn.ReLU(inplace=True),
            nn.Linear(exist_hidden, self.max_lanes),
        )
        self.register_buffer("class_weight", torch.tensor([self.background_weight] + [1.0] * self.max_lanes),
                             persistent=False)

    # ------------------------------------------------------------------ forward
    def forward(self, features: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        """seg (B, max_lanes + 1, H, W) class logits at the input size; exist_logits and exist (B, max_lanes),
        the latter the existence probabilities (sigmoid)."""
        hf, wf = self.fmap_size
        x = F.pad(features[-1], (0, 1, 0, 1))[:, :, :hf, :wf]
        x = self.message_passing(self.reduce(x))
        logits = self.classifier(self.dropout(x))  # (B, C, hf, wf)
        pooled = F.avg_pool2d(torch.softmax(logits, dim=1), 2)
        exist_logits = self.exist_fc(pooled.flatten(1))
        s = self.feature_stride
        h, w = self.image_size
        seg = F.interpolate(logits, size=(hf * s, wf * s), mode="bilinear",
                            align_corners=self.align_corners)[:, :, :h, :w]
        return {"seg": seg, "exist_logits": exist_logits, "exist": torch.sigmoid(exist_logits)}

    # ------------------------------------------------------------------ targets
    def encode(self, lanes: list[np.ndarray], meta: dict | None = None) -> dict[str, np.ndarray]:
        """GT lanes (input pixels) -> {"seg": uint8 (H, W) class map, "exist": float32 (max_lanes,)}."""
        return encode_lanes(lanes, self.image_size, self.max_lanes, self.line_width, self.slot_assignment)

    def loss(self, raw: dict, targets: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Weighted per-pixel cross-entropy (each image's weighted mean) + exist_loss_weight x existence BCE."""
        seg = raw["seg"]
        b = seg.shape[0]
        seg_t = targets["seg"].to(seg.device).long()
        exist_t = targets["exist"].to(seg.device).float()
        if seg_t.shape != (b, *self.image_size) or exist_t.shape != (b, self.max_lanes):
            raise ValueError(f"SCNNHead.loss: targets must be seg (B, {self.image_size[0]}, {self.image_size[1]}) and "
                             f"exist (B, {self.max_lanes}), got {tuple(seg_t.shape)} and {tuple(exist_t.shape)}")
        weight = self.class_weight.to(seg.device, torch.float32)
        nll = F.cross_entropy(seg.float(), seg_t, weight=weight, reduction="none")  # weight[t] * -log p_t
        seg_b = nll.flatten(1).sum(1) / weight[seg_t].flatten(1).sum(1)
        exist_b = F.binary_cross_entropy_with_logits(raw["exist_logits"].float(), exist_t, reduction="none").mean(1)
        per_sample = seg_b + self.exist_loss_weight * exist_b
        return {"loss": per_sample.mean(), "seg_loss": seg_b.mean(), "exist_loss": exist_b.mean(),
                "per_sample": per_sample}

    # ------------------------------------------------------------------ decode
    def decode(
        self,
        raw: dict,
        exist_threshold: float = 0.5,
        prob_threshold: float = 0.3,
        row_step: int = 1,
        min_points: int = 4,
        blur: int = 0,
        max_lanes: int | None = None,
        official_writer: str | None = None,
        *,
        with_scores: bool = False,
    ) -> list[list[np.ndarray]] | list[list[tuple[np.ndarray, float]]]:
        """Per image: lanes as (N, 2) float arrays in input pixels, y descending, left to right.

        A slot whose existence probability is above `exist_threshold` gives a lane (at most `max_lanes` per image,
        the least confident dropped as the official lane_pruning; None: all). Its probability map is box-blurred
        `blur` x `blur` first (0: not; the official: 9). `official_writer` None (ours): on every `row_step`-th row
        from the bottom its point is the refined argmax column where the map's maximum is above `prob_threshold`;
        "tusimple" / "culane": the official decoding's rows and whole-pixel x of that dataset's writer, x = 0 no
        point (codec.official_lane_points; `row_step` unused). A lane needs `min_points` points.
        `with_scores`: (lane, score) pairs, the score its slot's existence probability (what exist_threshold
        reads)."""
        if int(row_step) < 1:
            raise ValueError(f"SCNNHead.decode: row_step must be >= 1, got {row_step}")
        if official_writer is not None and official_writer not in OFFICIAL_WRITERS:
            raise ValueError(f"model.decode.official_writer={official_writer!r}: expected null or one of "
                             f"{', '.join(OFFICIAL_WRITERS)}")
        if int(blur) < 0 or (int(blur) > 1 and int(blur) % 2 == 0):
            raise ValueError(f"model.decode.blur: expected 0 or an odd kernel size, got {blur}")
        probs = torch.softmax(raw["seg"].detach().float(), dim=1)[:, 1:]
        exist = raw["exist"].detach().float().cpu().numpy()
        present = prune_lanes(exist, exist > exist_threshold, max_lanes)
        if official_writer is not None:
            lanes = official_lane_points(probs.cpu().numpy(), present, OFFICIAL_WRITERS[official_writer],
                                         prob_threshold, int(blur), int(min_points), with_slots=True)
        else:
            if int(blur) > 1:
                probs = torch.from_numpy(box_blur(probs.cpu().numpy(), int(blur))).to(probs.device)
            lanes = lane_points(probs, torch.from_numpy(present), prob_threshold, int(row_step), int(min_points),
                                with_slots=True)
        if with_scores:
            return [[(as_lane(lane), float(min(max(exist[b, slot], 0.0), 1.0))) for lane, slot in per_image]
                    for b, per_image in enumerate(lanes)]
        return [[as_lane(lane) for lane, _ in per_image] for per_image in lanes]
