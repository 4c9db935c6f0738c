"""LaneATT head (Tabelini et al., "Keep your Eyes on the Lane", CVPR 2021).

Anchor features are pooled from the last feature map along each line anchor, mixed by the
anchor attention, and classified / regressed (length + x offsets). ``forward`` returns raw
tensors only (ONNX-exportable); NMS and lane assembly live in ``decode``.

Distance thresholds (matching, NMS) are given in pixels at ``reference_width`` (640, the
official input width) and scaled by W / reference_width, so the defaults fit any input size.
As the official (lucastabelini/LaneATT, lib/models/laneatt.py): the anchors can be the topk most
used by the train split's lanes (anchor_selection=frequency, frequency.py; the task counts them,
tasks/detector/anchor_use.py), and the loss
is computed on the proposals a lane NMS keeps (15 px, top 3,000, no score threshold).
``fraction_scale`` (anchors.FRACTION_SCALES) says how the anchors' fractions of the image become pixels, and the
decoding's ``lane_points`` (decoding.LANE_POINTS) which points of a proposal make its lane: this
project's own configs keep the defaults (f x (W - 1), the points inside the image), the official_* experiments set
the official's (f x W, its proposals_to_pred).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from lanevil_train.lanes import row_proposal_to_lane
from lanevil_train.models.head import LaneHead, lanes_with_scores
from lanevil_train.models.laneatt.anchors import (
    TARGET_META,
    anchor_cut_indices,
    encode_lanes,
    feature_map_size,
    generate_anchors,
)
from lanevil_train.models.laneatt.decoding import check_lane_points, official_lane_points
from lanevil_train.models.laneatt.frequency import top_anchors
from lanevil_train.models.losses import anchor_target_distances, focal_loss
from lanevil_train.models.nms import lane_ends, lane_nms, lane_nms_batched
from lanevil_train.models.rows import FRACTION_SCALES, row_ys
from lanevil_train.rules import check_settings, existing_file, integer, null_or, number, one_of

# all: every anchor of the grid; frequency: the topk_anchors most used by the train split's lanes (the official)
ANCHOR_SELECTIONS = ("all", "frequency")


def _anchors_from_loaded_index(head: "LaneATTHead", incompatible_keys) -> None:
    """After load_state_dict: rebuild the anchor geometry from the loaded anchor_index buffer."""
    head._set_anchors(head.anchor_index)


def _read_frequency_file(path: str, anchors: int, geometry: str) -> np.ndarray:
    """The counts per anchor saved in `path` (the official repository's data/<dataset>_anchors_freq.pt: a 1-D
    tensor over the full anchor set, left, bottom, right), read weights-only; one per anchor of the head's `anchors`
    (its full set, which `geometry` says how it was made), in the file's own dtype; else a ValueError naming the
    file."""
    from lanevil_train.checkpoints import load_checkpoint_file

    where = f"model.head.anchor_frequency_file={path}"
    counts = load_checkpoint_file(path, "model.head.anchor_frequency_file")
    if not isinstance(counts, torch.Tensor) or counts.ndim != 1:
        is_tensor = isinstance(counts, torch.Tensor)
        found = f"a tensor of shape {tuple(counts.shape)}" if is_tensor else type(counts).__name__
        raise ValueError(f"{where}: expected a 1-D tensor of counts per anchor, got {found}")
    if len(counts) != anchors:
        raise ValueError(f"{where}: {len(counts)} counts, and this head has {anchors} anchors ({geometry}): the file "
                         f"was counted for another anchor set; the official files fit the official input size and "
                         f"anchor origins (lateral_n, bottom_n null)")
    return counts.numpy()


class LaneATTHead(LaneHead):
    """LaneATT: anchor feature pooling, anchor attention, classification and regression.

    It reads the last of the feature maps it is given (the stride-32 stage in its paper)."""

    # The constructor's parameters with a range, and what a good value of each is: checked by the constructor,
    # and by the config check under model.head.* before any work (one place to say it).
    SETTINGS = {
        "n_offsets": integer(2),
        "anchor_feat_channels": integer(1),
        "max_lanes": integer(1),
        "topk_anchors": null_or(integer(2)),
        "lateral_n": null_or(integer(1)),
        "bottom_n": null_or(integer(1)),
        "pos_threshold": number(0),
        "neg_threshold": number(0),
        "reference_width": number(0, low_open=True),
        "cls_loss_weight": number(0),
        "focal_alpha": number(0, 1),
        "focal_gamma": number(0),
        "anchor_selection": one_of(*ANCHOR_SELECTIONS),
        "fraction_scale": one_of(*FRACTION_SCALES),
        "frequency_threshold": number(0),
        "train_nms_threshold": null_or(number(0, low_open=True)),  # null: no NMS before the loss
        "train_nms_topk": integer(1),
        "anchor_frequency_file": null_or(existing_file("anchor frequency file (a tensor of counts per anchor, e.g. "
                                                       "the official data/tusimple_anchors_freq.pt)")),
    }

    def __init__(
        self,
        in_channels: list[int],
        in_strides: list[int],
        image_size: tuple[int, int],
        n_offsets: int = 72,
        anchor_feat_channels: int = 64,
        max_lanes: int = 6,
        fraction_scale: str = "last_pixel",
        anchor_selection: str = "all",
        topk_anchors: int | None = None,
        lateral_n: int | None = None,
        bottom_n: int | None = None,
        anchor_frequency: np.ndarray | None = None,
        anchor_frequency_file: str | None = None,
        frequency_threshold: float = 30.0,
        pos_threshold: float = 15.0,
        neg_threshold: float = 20.0,
        train_nms_threshold: float | None = 15.0,
        train_nms_topk: int = 3000,
        reference_width: float = 640.0,
        cls_loss_weight: float = 10.0,
        focal_alpha: float = 0.25,
        focal_gamma: float = 2.0,
    ) -> None:
        check_settings(self.SETTINGS, locals(), "model.head")
        super().__init__(in_channels, in_strides, image_size)
        h, w = self.image_size
        feature_stride = self.in_strides[-1]
        if neg_threshold < pos_threshold:
            raise ValueError(f"LaneATTHead: neg_threshold {neg_threshold} must be >= pos_threshold {pos_threshold}")
        if anchor_selection == "frequency" and topk_anchors is None:
            raise ValueError("topk_anchors: anchor_selection=frequency keeps the topk_anchors most used anchors; "
                             "set it (the official: 1000) or use anchor_selection=all")
        self.n_offsets = n_offsets
        self.max_lanes = max_lanes
        self.fraction_scale = fraction_scale
        self.feature_stride = feature_stride
        self.threshold_scale = w / reference_width
        self.pos_threshold = pos_threshold * self.threshold_scale
        self.neg_threshold = neg_threshold * self.threshold_scale
        self.frequency_threshold = frequency_threshold * self.threshold_scale
        self.train_nms_threshold = None if train_nms_threshold is None else train_nms_threshold * self.threshold_scale
        self.train_nms_topk = train_nms_topk
        self.cls_loss_weight = cls_loss_weight
        self.focal_alpha, self.focal_gamma = focal_alpha, focal_gamma

        self.all_anchors = generate_anchors(self.image_size, n_offsets, lateral_n, bottom_n, scale=fraction_scale)
        total = len(self.all_anchors)
        if anchor_selection == "all" and topk_anchors is not None and topk_anchors < total:
            raise ValueError(f"topk_anchors: {topk_anchors} of the {total} anchors with anchor_selection=all; "
                             "choose them with anchor_selection=frequency, or set topk_anchors=null")
        # frequency selection: until the train split's counts arrive (use_frequency), an even spread over the
        # anchor list stands in; the chosen indices are a persistent buffer, so a checkpoint rebuilds the same net
        self.anchor_selection = anchor_selection if topk_anchors is not None and topk_anchors < total else "all"
        n_kept = total if self.anchor_selection == "all" else topk_anchors
        if n_kept < 2:
            raise ValueError("LaneATTHead: need at least 2 anchors")
        if self.anchor_selection == "all":
            index = np.arange(total)
        else:
            index = np.round(np.linspace(0, total - 1, n_kept)).astype(np.int64)
        self.register_buffer("anchor_index", torch.from_numpy(index).long())
        self.register_buffer("anchors_chosen", torch.tensor(int(self.anchor_selection == "all")))
        self.n_anchors = n_kept
        self.fmap_size = feature_map_size(self.image_size, feature_stride)
        self._set_anchors(index)
        if anchor_frequency_file is not None:
            if self.anchor_selection != "frequency":
                raise ValueError("model.head.anchor_frequency_file: its counts choose the topk_anchors anchors; set "
                                 "anchor_selection=frequency and topk_anchors (the official: 1000)")
            geometry = (f"n_offsets {n_offsets}, lateral_n {lateral_n}, bottom_n {bottom_n} at {h}x{w}, "
                        f"data.input_size")
            # an official file: its tied counts ordered as the official orders them (frequency.TIE_ORDERS)
            self.use_frequency(_read_frequency_file(anchor_frequency_file, len(self.all_anchors), geometry), "torch")
        elif anchor_frequency is not None:
            self.use_frequency(anchor_frequency)
        self.register_load_state_dict_post_hook(_anchors_from_loaded_index)
        self.row_ys = row_ys(h, n_offsets, fraction_scale)

        hf, _ = self.fmap_size
        feat_dim = anchor_feat_channels * hf
        self.conv1 = nn.Conv2d(self.in_channels[-1], anchor_feat_channels, kernel_size=1)
        self.attention_layer = nn.Linear(feat_dim, self.n_anchors - 1)
        self.cls_layer = nn.Linear(2 * feat_dim, 2)
        self.reg_layer = nn.Linear(2 * feat_dim, n_offsets + 1)
        for layer in (self.cls_layer, self.reg_layer):
            nn.init.normal_(layer.weight, 0.0, 0.001)
            nn.init.zeros_(layer.bias)

    # ------------------------------------------------------------------ anchors
    def _set_anchors(self, index) -> None:
        """The anchor geometry buffers (not saved: derived from anchor_index) for the anchors at `index`."""
        index = np.asarray(torch.as_tensor(index).cpu(), dtype=np.int64)
        if index.shape != (self.n_anchors,) or index.min() < 0 or index.max() >= len(self.all_anchors):
            raise ValueError(f"LaneATTHead: anchor_index must be {self.n_anchors} indices into the "
                             f"{len(self.all_anchors)} anchors, got shape {index.shape}")
        anchors = self.all_anchors.subset(index)
        cols, valid, _ = anchor_cut_indices(anchors, self.image_size, self.feature_stride)
        hf = self.fmap_size[0]
        device = self.anchor_index.device
        buffers = {
            "anchor_xs": torch.from_numpy(anchors.xs).float(),
            "anchor_starts": torch.from_numpy(anchors.starts),
            "cut_cols": torch.from_numpy(cols),
            "cut_rows": torch.arange(hf)[None, :].expand(self.n_anchors, hf).contiguous(),
            "cut_valid": torch.from_numpy(valid),
        }
        for name, value in buffers.items():
            self.register_buffer(name, value.to(device), persistent=False)
        self.anchor_index.copy_(torch.from_numpy(index))

    def use_frequency(self, frequency, ties: str = "index") -> None:
        """Keep the topk_anchors anchors the training lanes use most (frequency: a count per anchor of the full
        set), most used first as the official orders them; equal counts ordered as `ties` says
        (frequency.TIE_ORDERS)."""
        freq = np.asarray(frequency)
        if freq.shape != (len(self.all_anchors),):
            raise ValueError(f"LaneATTHead: anchor_frequency has shape {freq.shape}, "
                             f"expected ({len(self.all_anchors)},)")
        if self.anchor_selection == "frequency":
            self._set_anchors(top_anchors(freq, self.n_anchors, ties))
        self.anchors_chosen.fill_(1)

    def wants_anchor_use(self) -> bool:
        """Whether the head waits for the train split's anchor-use counts (use_frequency): anchor_selection=frequency
        and the anchors not chosen yet (a checkpoint's or a frequency file's are kept)."""
        return self.anchor_selection == "frequency" and not bool(self.anchors_chosen)

    def anchor_use_settings(self) -> dict:
        """What anchors_used's counts depend on besides the images' lanes (a cached count's fingerprint): the full
        anchor set, the rows, the match distance and the fraction scale."""
        full = self.all_anchors
        return {"anchors": len(full), "n_offsets": self.n_offsets, "threshold": self.frequency_threshold,
                "scale": self.fraction_scale, "first_xs": full.xs[:, 0].round(3).tolist()[:8]}

    def anchors_used(self, lanes: list[np.ndarray]) -> np.ndarray:
        """Per anchor of the full set, whether one image's lanes (input pixels) use it: its mean x distance to one of
        them, over their common rows, is below frequency_threshold (a positive of the official's matching at
        t_pos, as utils/gen_anchor_mask.py's save_mask counts it)."""
        full = self.all_anchors
        if not lanes:
            return np.zeros(len(full), dtype=bool)
        xs, starts = torch.from_numpy(full.xs).float(), torch.from_numpy(full.starts)
        t = torch.from_numpy(encode_lanes(lanes, self.image_size, self.n_offsets, len(lanes),
                                          self.fraction_scale))[None].float()
        dist = anchor_target_distances(xs, starts, t[..., 0], t[..., 1], t[..., 2], t[..., TARGET_META:])
        return (dist[0].min(dim=-1).values < self.frequency_threshold).numpy()

    # ------------------------------------------------------------------ forward
    def forward(self, features: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        """Raw outputs: cls_logits (B, A, 2), length (B, A) in rows, xs (B, A, S) in input pixels."""
        x = self.conv1(features[-1])
        hf, wf = self.fmap_size
        # zero-pad then crop to H // stride x W // stride (the official fmap_h, fmap_w): a ResNet's extra
        # bottom row at sizes that are not multiples of the stride is dropped, as the official never reads
        # it; unconditional, so the graph has no shape-dependent branch
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
        return {"lanes": encode_lanes(lanes, self.image_size, self.n_offsets, self.max_lanes, self.fraction_scale)}

    def match(self, targets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Anchor assignment: positives (B, A), negatives (B, A), index of the matched target (B, A)."""
        t = targets.to(self.anchor_xs.device).float()
        dist = anchor_target_distances(
            self.anchor_xs, self.anchor_starts, t[..., 0], t[..., 1], t[..., 2], t[..., TARGET_META:]
        )
        best, idx = dist.min(dim=-1)
        return best < self.pos_threshold, best > self.neg_threshold, idx

    def train_nms_keep(self, raw: dict) -> torch.Tensor:
        """(B, A) bool: the proposals the official's training NMS keeps (train_nms_threshold px at 640 wide, the
        top train_nms_topk, no score threshold); all of them when train_nms_threshold is null."""
        scores = torch.softmax(raw["cls_logits"].detach().float(), dim=-1)[..., 1]
        if self.train_nms_threshold is None:
            return torch.ones_like(scores, dtype=torch.bool)
        return lane_nms_batched(raw["xs"].detach(), self.anchor_starts, raw["length"].detach(), scores,
                                self.train_nms_threshold, self.train_nms_topk)

    def loss(self, raw: dict, targets: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Focal classification + smooth-L1 regression of positives, per image as the official, over the
        proposals the training NMS keeps (the official computes its loss on the NMS output)."""
        targets = targets["lanes"].to(raw["xs"].device).float()
        if targets.ndim != 3 or targets.shape[-1] != TARGET_META + self.n_offsets:
            raise ValueError(
                f"LaneATTHead.loss: targets must be (B, max_lanes, {TARGET_META + self.n_offsets}), "
                f"got {tuple(targets.shape)}"
            )
        with torch.no_grad():
            keep = self.train_nms_keep(raw)
            pos, neg, idx = self.match(targets)
            pos, neg = pos & keep, neg & keep
            matched = torch.gather(targets, 1, idx[..., None].expand(-1, -1, targets.shape[-1]))  # (B, A, D)
            t_end = matched[..., 1] + matched[..., 2] - 1
            a_start = self.anchor_starts[None, :].float()
            len_target = t_end - a_start + 1
            rows = torch.arange(self.n_offsets, device=targets.device)
            row_ok = (rows >= a_start[..., None]) & (rows <= t_end[..., None])  # (B, A, S)
        n_pos = pos.sum(dim=1).float()
        focal = focal_loss(raw["cls_logits"], pos.long(), self.focal_alpha, self.focal_gamma)
        # an image with no positive left: every kept proposal is a negative, as the official's edge cases
        scored = torch.where((n_pos > 0)[:, None], pos | neg, keep)
        cls_b = (focal * scored).sum(dim=1) / n_pos.clamp(min=1)
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
        lane_points: str = "inside",
        *,
        with_scores: bool = False,
    ) -> list[list[np.ndarray]] | list[list[tuple[np.ndarray, float]]]:
        """Per image: lanes as (N, 2) float arrays in input pixels, y descending, left to right.

        The proposals scoring above conf_threshold, lane NMS (nms_threshold px at 640 wide, at most nms_topk, or
        max_lanes); of each, the points `lane_points` says (decoding.LANE_POINTS): "inside" the image
        (plus its border crossing), or "official", those the official proposals_to_pred keeps.
        `with_scores`: (lane, score) pairs, the score the kept proposal's softmax class score (the one
        conf_threshold and the NMS read)."""
        check_lane_points(lane_points)
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
            lanes, lane_scores = [], []
            for k, end in zip(keep.cpu().numpy(), ends):
                if lane_points == "official":
                    lane = official_lane_points(xs[b, k].cpu().numpy(), self.row_ys, int(starts[k]),
                                                    float(lengths[b, k]), self.image_size[1])
                else:
                    lane = row_proposal_to_lane(xs[b, k].cpu().numpy().astype(np.float64), self.row_ys,
                                                int(starts[k]), int(end), self.image_size[1])
                if lane is not None:
                    lanes.append(lane)
                    lane_scores.append(scores[b, k].item())
            out.append(lanes_with_scores(lanes, lane_scores, with_scores))
        return out
