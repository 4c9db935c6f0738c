"""UFLD head (Qin et al., "Ultra Fast Structure-aware Deep Lane Detection", ECCV 2020; version 1).

Lane detection as row-wise classification on global features: for each of ``max_lanes`` lane slots and each
row anchor, pick the grid cell the lane crosses, or the extra "no lane" cell. As the paper: a 1x1 convolution
reduces the last (stride-32) map to 8 channels, which is flattened and fed to two fully connected layers
(hidden 2048) whose output is reshaped to (num_cells + 1, num_rows, max_lanes). The FC layers tie the head to
the input size, which it gets at construction. During training an auxiliary segmentation branch on the
multi-scale features (strides 8, 16, 32, the paper's aux header) predicts each lane slot as a class map at the
finest stride; it is computed only in train mode, so the exported (eval) graph is the classification head alone.

Losses: focal classification over the cells, the structural similarity and shape losses, and cross-entropy of
the aux segmentation (losses.py). Decoding takes the expectation of the location under the softmax over the
cells, on the rows where the arg-max is not "no lane", mapped to x as the official TuSimple writer does
(codec.cell_to_x), and keeps a lane with at least ``min_points`` points. The cells are the official ones
(positions linspace(0, W - 1, num_cells), codec.py). ``decode(official_writer="tusimple" | "culane")`` gives
exactly the points the official test writers write (codec.official_writer_points; the official_ufld_*
experiments set it, with the end extension off and ``model.row_sampling: points``, so that no row between two
points is filled in).

Where we chose: lanes fill the slots by their x at the image bottom, in left-to-right order and centred on the
camera (lanes.assign_slots; the paper's datasets give fixed lane indices); row anchors are fractions of the
height; the shape loss counts only rows holding the ground-truth lane (losses.py); decoding extends each
lane's ends to the neighbouring row anchors (decode's extend_ends) and clips x to the image (the official writers
leave the last cell's x, past the right edge, as it is). The loss weights default to the official TuSimple
config (similarity 1, shape 0, aux 1; its CULane config sets similarity 0): a shape loss weighted 1 (in cell
units) slowed the classification's start a lot in our small runs, which fits the official configs leaving it off.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from lanevil_train.lanes import SLOT_ASSIGNMENTS, as_lane
from lanevil_train.models.head import LaneHead, lanes_with_scores
from lanevil_train.models.ufld.codec import (
    OFFICIAL_WRITERS,
    cell_to_x,
    cell_width,
    draw_seg_mask,
    encode_cls_labels,
    official_writer_points,
    row_anchor_fractions,
    row_ys,
)
from lanevil_train.models.ufld.losses import (
    classification_loss,
    expected_locations,
    segmentation_loss,
    shape_loss,
    similarity_loss,
)
from lanevil_train.rules import boolean, check_settings, integer, null_or, number, one_of


def _conv_bn_relu(in_channels: int, out_channels: int, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(in_channels, out_channels, 3, padding=dilation, dilation=dilation, bias=False),
                         nn.BatchNorm2d(out_channels), nn.ReLU(inplace=True))


class UFLDAuxSegmentation(nn.Module):
    """The paper's auxiliary segmentation branch: a 3x3 conv-BN-ReLU header per feature map (4, 3 and 2 layers
    on strides 8, 16 and 32 as the official; one fewer per coarser map, at least 2), the coarser maps resized
    (bilinear) to the finest, concatenated, then four dilated (2, 2, 2, 4) conv-BN-ReLU layers and a 1x1
    classifier into num_classes (lane slots + background) at the finest map's resolution."""

    def __init__(self, in_channels: Sequence[int], num_classes: int, channels: int = 128) -> None:
        super().__init__()
        n = len(in_channels)
        depths = [max(2, n + 1 - i) for i in range(n)]  # 4, 3, 2 for strides 8, 16, 32
        self.headers = nn.ModuleList(
            nn.Sequential(_conv_bn_relu(c, channels), *[_conv_bn_relu(channels, channels) for _ in range(depth - 1)])
            for c, depth in zip(in_channels, depths)
        )
        self.combine = nn.Sequential(
            _conv_bn_relu(n * channels, 2 * channels, dilation=2),
            _conv_bn_relu(2 * channels, channels, dilation=2),
            _conv_bn_relu(channels, channels, dilation=2),
            _conv_bn_relu(channels, channels, dilation=4),
            nn.Conv2d(channels, num_classes, 1),
        )

    def forward(self, features: list[torch.Tensor]) -> torch.Tensor:
        size = features[0].shape[-2:]
        maps = [header(f) for header, f in zip(self.headers, features)]
        maps = maps[:1] + [F.interpolate(m, size=size, mode="bilinear", align_corners=False) for m in maps[1:]]
        return self.combine(torch.cat(maps, dim=1))


class UFLDHead(LaneHead):
    """UFLD: row-anchor classification with structural losses and a training-only aux segmentation.

    It reads the last of the feature maps it is given (stride 32 in the paper); the aux branch reads all of them
    (strides 8, 16, 32) and predicts at the first one's stride.
    """

    # The constructor's parameters with a range, and what a good value of each is: checked by the constructor,
    # and by the config check under model.head.* before any work (one place to say it).
    SETTINGS = {
        "num_cells": integer(2),
        "num_rows": null_or(integer(3)),
        "max_lanes": integer(1),
        "pool_channels": integer(1),
        "hidden_dim": integer(1),
        "use_aux": boolean(),
        "aux_channels": integer(1),
        "aux_line_width": integer(1),
        "slot_assignment": one_of(*SLOT_ASSIGNMENTS),
        "extend_to_bottom": boolean(),
        "focal_gamma": number(0),
        "cls_loss_weight": number(0),
        "sim_loss_weight": number(0),
        "shape_loss_weight": number(0),
        "aux_loss_weight": number(0),
    }

    def __init__(
        self,
        in_channels: list[int],
        in_strides: list[int],
        image_size: tuple[int, int],
        num_cells: int = 100,
        row_anchors: str | Sequence[float] = "tusimple",
        num_rows: int | None = None,
        max_lanes: int = 4,
        pool_channels: int = 8,
        hidden_dim: int = 2048,
        use_aux: bool = True,
        aux_channels: int = 128,
        aux_line_width: int = 1,
        slot_assignment: str = "ego",
        extend_to_bottom: bool = True,
        focal_gamma: float = 2.0,
        cls_loss_weight: float = 1.0,
        sim_loss_weight: float = 1.0,
        shape_loss_weight: float = 0.0,
        aux_loss_weight: float = 1.0,
    ) -> None:
        check_settings(self.SETTINGS, locals(), "model.head")
        super().__init__(in_channels, in_strides, image_size)
        h, w = self.image_size
        try:
            self.row_fractions = row_anchor_fractions(row_anchors, num_rows)
        except ValueError as error:
            raise ValueError(f"UFLDHead: {error}") from None
        if w < num_cells + 1:
            raise ValueError(f"UFLDHead: num_cells={num_cells} needs an input at least {num_cells + 1} px wide, "
                             f"got {w}")
        self.num_cells = int(num_cells)
        self.num_rows = len(self.row_fractions)
        self.max_lanes = int(max_lanes)
        self.row_ys = row_ys(self.row_fractions, h)
        self.cell_width = cell_width(w, self.num_cells)
        self.use_aux = bool(use_aux)
        self.aux_line_width = int(aux_line_width)
        self.slot_assignment = slot_assignment
        self.extend_to_bottom = bool(extend_to_bottom)
        self.focal_gamma = float(focal_gamma)
        self.weights = {"cls": float(cls_loss_weight), "sim": float(sim_loss_weight),
                        "shape": float(shape_loss_weight), "aux": float(aux_loss_weight)}

        stride = self.in_strides[-1]
        self.fmap_size = (math.ceil(h / stride), math.ceil(w / stride))
        self.pool = nn.Conv2d(self.in_channels[-1], int(pool_channels), kernel_size=1)
        self.cls = nn.Sequential(
            nn.Linear(int(pool_channels) * self.fmap_size[0] * self.fmap_size[1], int(hidden_dim)),
            nn.ReLU(inplace=True),
            nn.Linear(int(hidden_dim), (self.num_cells + 1) * self.num_rows * self.max_lanes),
        )
        self.aux_stride = self.in_strides[0]
        self.aux = (UFLDAuxSegmentation(self.in_channels, self.max_lanes + 1, int(aux_channels))
                    if self.use_aux else None)
        self._init_weights()

    def _init_weights(self) -> None:
        """As the official: Kaiming (ReLU) convolutions, BN 1 / 0, fully connected weights N(0, 0.01)."""
        for module in [self.cls] + ([self.aux] if self.aux is not None else []):
            for m in module.modules():
                if isinstance(m, nn.Conv2d):
                    nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
                    if m.bias is not None:
                        nn.init.zeros_(m.bias)
                elif isinstance(m, nn.BatchNorm2d):
                    nn.init.ones_(m.weight)
                    nn.init.zeros_(m.bias)
                elif isinstance(m, nn.Linear):
                    nn.init.normal_(m.weight, 0.0, 0.01)
                    nn.init.zeros_(m.bias)

    # ------------------------------------------------------------------ forward
    def forward(self, features: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        """cls_logits (B, num_cells + 1, num_rows, max_lanes), rows top first; in train mode with the aux branch
        also seg_logits (B, max_lanes + 1, h, w) at the first feature map's stride."""
        hf, wf = self.fmap_size
        x = self.pool(features[-1])
        # zero-pad then crop to the expected map size (VGG floors odd sizes where ResNet rounds up);
        # unconditional, so the graph has no shape-dependent branch
        x = F.pad(x, (0, wf, 0, hf))[:, :, :hf, :wf]
        logits = self.cls(x.flatten(1)).view(-1, self.num_cells + 1, self.num_rows, self.max_lanes)
        out = {"cls_logits": logits}
        if self.aux is not None and self.training:
            out["seg_logits"] = self.aux(features)
        return out

    # ------------------------------------------------------------------ targets
    def encode(self, lanes: list[np.ndarray], meta: dict | None = None) -> dict[str, np.ndarray]:
        """GT lanes (input pixels) -> {"cls_labels": int64 (num_rows, max_lanes), cell per row and slot,
        num_cells = no lane; with the aux branch "seg": uint8 (ceil(H / s), ceil(W / s)) slot + 1 per lane}."""
        labels, slotted = encode_cls_labels(lanes, self.row_fractions, self.image_size, self.num_cells,
                                            self.max_lanes, self.slot_assignment, self.extend_to_bottom)
        out = {"cls_labels": labels}
        if self.use_aux:
            out["seg"] = draw_seg_mask(slotted, self.image_size, self.aux_stride, self.aux_line_width)
        return out

    def loss(self, raw: dict, targets: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Weighted sum per image of the focal classification, similarity, shape and aux segmentation losses.

        The aux loss counts only when raw holds seg_logits (train mode); otherwise it is 0."""
        logits = raw["cls_logits"]
        labels = targets["cls_labels"].to(logits.device).long()
        want = (logits.shape[0], self.num_rows, self.max_lanes)
        if tuple(labels.shape) != want:
            raise ValueError(f"UFLDHead.loss: targets['cls_labels'] must be (B, num_rows, max_lanes) = {want}, got "
                             f"{tuple(labels.shape)}")
        parts = {
            "cls_loss": classification_loss(logits, labels, self.focal_gamma),
            "sim_loss": similarity_loss(logits),
            "shape_loss": shape_loss(logits, labels),
        }
        if "seg_logits" in raw:
            if "seg" not in targets:
                raise ValueError("UFLDHead.loss: raw has seg_logits but targets have no 'seg' (encode with use_aux)")
            parts["aux_loss"] = segmentation_loss(raw["seg_logits"], targets["seg"].to(logits.device))
        else:
            parts["aux_loss"] = torch.zeros_like(parts["cls_loss"])
        w = self.weights
        per_sample = (w["cls"] * parts["cls_loss"] + w["sim"] * parts["sim_loss"] + w["shape"] * parts["shape_loss"]
                      + w["aux"] * parts["aux_loss"])
        return {"loss": per_sample.mean(), "per_sample": per_sample, **{k: v.mean() for k, v in parts.items()}}

    # ------------------------------------------------------------------ decode
    def decode(self, raw: dict, min_points: int = 3, extend_ends: bool = True, local_width: int | None = None,
               official_writer: str | None = None, *,
               with_scores: bool = False) -> list[list[np.ndarray]] | list[list[tuple[np.ndarray, float]]]:
        """Per image: lanes as (N, 2) float arrays in input pixels, y descending, left to right.

        A slot has a point on each row whose arg-max over the num_cells + 1 classes is not "no lane"; its x is
        the expected cell index under the softmax over the cells (`local_width` None, v1's writer; an int k: over
        the arg-max cell +- k only, UFLD v2's). `official_writer` None (ours): x mapped as the official TuSimple
        writer (codec.cell_to_x) and clipped to [0, W - 1], y the row anchors'; "tusimple" / "culane": exactly the
        points the official writer of that dataset writes (codec.official_writer_points: its x scale and whole
        pixels, unclipped; on CULane its rows), in input pixels. A slot with fewer than `min_points` points is
        dropped (the official CULane writer keeps lanes with more than 2, its TuSimple writer every lane).
        `extend_ends`: a lane's true ends lie between its end rows and the next row anchors (or the image bottom
        below the last row), so each end is extended straight to that neighbouring row, stopping where it leaves
        the image (our choice; the official writers stop at the end rows).
        `with_scores`: (lane, score) pairs. UFLD gives a lane no score of its own; its score here is the mean, over
        the rows where the slot has a point, of the probability of the cell chosen there (the arg-max class, under
        the softmax over the num_cells cells and "no lane").
        """
        if official_writer is not None and official_writer not in OFFICIAL_WRITERS:
            raise ValueError(f"model.decode.official_writer={official_writer!r}: expected null or one of "
                             f"{', '.join(OFFICIAL_WRITERS)}")
        logits = raw["cls_logits"].detach().float()
        present = (logits.argmax(dim=1) != self.num_cells).cpu().numpy()  # (B, R, L)
        # the chosen class's probability (softmax over cells and no-lane) at each row and slot: each lane's score
        chosen = torch.softmax(logits, dim=1).amax(dim=1).cpu().numpy() if with_scores else None
        h, w = self.image_size
        ys = self.row_ys
        if official_writer is None:
            xs = cell_to_x(expected_locations(logits, local_width), w, self.num_cells).clamp(0.0, w - 1.0)
            xs = xs.cpu().numpy()
        else:
            locations = expected_locations(logits, local_width, torch.float64).cpu().numpy()
            xs, writer_ys = official_writer_points(locations, self.num_rows, self.image_size, self.num_cells,
                                                   official_writer)
            ys = ys if writer_ys is None else writer_ys
        out: list[list[np.ndarray]] = []
        for b in range(logits.shape[0]):
            lanes, lane_scores = [], []
            for k in range(self.max_lanes):
                rows = np.flatnonzero(present[b, :, k])
                if len(rows) < max(int(min_points), 1):
                    continue
                pts = np.stack([xs[b, rows, k], ys[rows]], axis=1)  # top first
                if extend_ends and len(rows) >= 2:
                    top_y = ys[rows[0] - 1] if rows[0] > 0 else None
                    bottom_y = ys[rows[-1] + 1] if rows[-1] + 1 < self.num_rows else h - 1.0
                    ends = [self._extend(pts[1], pts[0], top_y), self._extend(pts[-2], pts[-1], bottom_y)]
                    pts = np.concatenate([e for e in (ends[0], pts, ends[1]) if e is not None])
                lanes.append(as_lane(pts))
                lane_scores.append(float(chosen[b, rows, k].mean()) if with_scores else 0.0)
            out.append(lanes_with_scores(lanes, lane_scores, with_scores))
        return out

    def _extend(self, inner: np.ndarray, end: np.ndarray, y: float | None) -> np.ndarray | None:
        """The point on the line inner -> end at row y, cut at the image's left or right border; None if none."""
        if y is None or y == end[1] or inner[1] == end[1]:
            return None
        w = self.image_size[1]
        t = (y - end[1]) / (end[1] - inner[1])  # > 0: beyond `end`
        x = end[0] + t * (end[0] - inner[0])
        if 0.0 <= x <= w - 1:
            return np.array([[x, y]])
        border = 0.0 if x < 0 else w - 1.0
        s = (border - end[0]) / (x - end[0])  # fraction of the way to the crossing
        return np.array([[border, end[1] + s * (y - end[1])]]) if s > 0 else None
