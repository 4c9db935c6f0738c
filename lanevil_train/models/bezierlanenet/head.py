"""BezierLaneNet head (Feng et al., "Rethinking Efficient Lane Detection via Curve Modeling", CVPR 2022).

The official network (pytorch-auto-drive ``BezierLaneNet``) reads the stride-16 ResNet layer3 map and runs:
two dilated bottleneck blocks (YOLOF's: 1x1 down to 64 channels, a 3x3 convolution dilated 4 then 8, 1x1 back,
each BN + ReLU, a residual sum); the feature flip fusion (the map through a 1x1 conv + BN, added to its horizontal
mirror image through a 3x3 modulated deformable convolution (DCNv2) + BN whose offsets and masks are predicted by
a 3x3 conv of both, then a ReLU); an average over the height, giving a 1-D sequence of W/16 queries; two 1-D 3x3
convs + BN + ReLU shared by the branches; per query a 1x1 conv to one existence logit and one to 8 parameters, the
4 control points (x, y) of a cubic Bezier curve, normalised by the input width and height. An auxiliary binary
lane segmentation (3x3 conv to 64 + BN + ReLU, 1x1 conv to 1, on the layer3 map before the dilated blocks) is
trained alongside and dropped at inference.

Choices: the deformable convolution is plain torch (each of the 9 taps read by bilinear grid_sample at its offset
position, zero outside, times its mask, then one matrix product with the kernel), so it exports to ONNX; its
offsets follow mmcv's layout (channel 2k the y and 2k + 1 the x offset of tap k, row-major taps, then 9 mask
channels) and start at zero as the official. The segmentation logits are computed only in training mode (so export
sees the same keys as eval), and its loss is zero when they are absent. A backbone map that is not ``channels``
wide (ResNet-50's 1024) goes through a 1x1 conv + BN + ReLU first (the official's optional "reducer"). Under
mixed precision (autocast) the fusion runs in float32, as the official's (``bezier_lane_net.py`` l. 59-60). The
official trains the offset convolution (``conv_offset``: offsets and masks) at 0.1x the rate; the family config
gives it through model.lr_multipliers. The local-maximum window of the matching and the decoding is by default
(``"auto"``) the official 9 scaled to the query count (loss.scaled_window): 9 would let at most 4
lanes survive among the 20 queries of a 320 px input.
Targets, matching and loss: loss.py.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from lanevil_train.lanes import as_lane
from lanevil_train.models.bezierlanenet.bezier import (
    OFFICIAL_CULANE_SIZE,
    OFFICIAL_TUSIMPLE_SIZE,
    official_culane_points,
    official_tusimple_points,
    x_at_rows,
)
from lanevil_train.models.bezierlanenet.loss import (
    AUTO,
    bezier_losses,
    encode_targets,
    local_maximum,
    resolve_window,
)
from lanevil_train.models.head import LaneHead, lanes_with_scores
from lanevil_train.models.nms import prune_lanes
from lanevil_train.models.sampling import sample_at
from lanevil_train.rules import any_of, check_settings, int_list, integer, number, one_of

# A curve's end read as covering a row up to this many pixels beyond it: the least-squares fit moves a lane's ends
# by a fraction of a pixel, which would otherwise drop the bottom row (the official TuSimple decoding takes the
# nearest of its sampled points within 5 px of each row instead).
ROW_TOLERANCE = 1.0


def _conv_bn(c_in: int, c_out: int, kernel: int = 1, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, kernel, padding=dilation * (kernel // 2), dilation=dilation),
                         nn.BatchNorm2d(c_out))


class DilatedBottleneck(nn.Module):
    """YOLOF's dilated residual block as the official: 1x1 (to mid) -> 3x3 dilated -> 1x1 (back), each conv + BN
    + ReLU (the last ReLU before the residual sum), no downsampling."""

    def __init__(self, channels: int, mid_channels: int, dilation: int) -> None:
        super().__init__()
        self.conv1 = _conv_bn(channels, mid_channels)
        self.conv2 = _conv_bn(mid_channels, mid_channels, 3, dilation)
        self.conv3 = _conv_bn(mid_channels, channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu(self.conv1(x))
        out = F.relu(self.conv2(out))
        return F.relu(self.conv3(out)) + x


class ModulatedDeformConv3x3(nn.Module):
    """DCNv2 3x3 (stride 1, padding 1) of `x`, its offsets and masks predicted from cat(x, ref) by a 3x3 conv that
    starts at zero (offsets 0, masks 0.5), in plain torch."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.empty(channels, channels, 3, 3))
        self.bias = nn.Parameter(torch.zeros(channels))
        nn.init.kaiming_uniform_(self.weight, a=math.sqrt(5))
        self.conv_offset = nn.Conv2d(2 * channels, 3 * 9, 3, padding=1)
        nn.init.zeros_(self.conv_offset.weight)
        nn.init.zeros_(self.conv_offset.bias)
        taps = torch.tensor([(ky - 1.0, kx - 1.0) for ky in range(3) for kx in range(3)])  # row-major (dy, dx)
        self.register_buffer("tap_dy", taps[:, 0].reshape(1, 9, 1, 1), persistent=False)
        self.register_buffer("tap_dx", taps[:, 1].reshape(1, 9, 1, 1), persistent=False)

    def forward(self, x: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        out = self.conv_offset(torch.cat([x, ref], dim=1))
        return self.deform(x, out[:, 0:18:2], out[:, 1:18:2], torch.sigmoid(out[:, 18:]))

    def deform(self, x: torch.Tensor, dy: torch.Tensor, dx: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """The deformable conv of x (B, C, h, w) with per-tap offsets dy, dx and masks (B, 9, h, w)."""
        b, h, w = x.shape[0], x.shape[2], x.shape[3]
        rows = torch.arange(h, device=x.device, dtype=x.dtype).reshape(1, 1, h, 1)
        cols = torch.arange(w, device=x.device, dtype=x.dtype).reshape(1, 1, 1, w)
        ys = (rows + self.tap_dy + dy).expand(b, 9, h, w)
        xs = (cols + self.tap_dx + dx).expand(b, 9, h, w)
        taps = sample_at(x, xs, ys, (h, w)) * mask[:, None]  # (B, C, 9, h, w), zero outside the map
        # (C_in, tap) flattened in the order of the kernel's (C_out, C_in, 3, 3) layout
        return F.conv2d(taps.flatten(1, 2), self.weight.flatten(1)[..., None, None], self.bias)


class FeatureFlipFusion(nn.Module):
    """relu(BN(conv1x1(f)) + BN(DCN(flip(f), offsets from cat(flip(f), BN(conv1x1(f)))))): the paper's feature
    flip fusion, lanes being roughly symmetric about the image centre."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.proj1 = _conv_bn(channels, channels)
        self.proj2_conv = ModulatedDeformConv3x3(channels)
        self.proj2_norm = nn.BatchNorm2d(channels)

    def forward(self, feature: torch.Tensor) -> torch.Tensor:
        flipped = torch.flip(feature, dims=[-1])
        projected = self.proj1(feature)
        return F.relu(projected + self.proj2_norm(self.proj2_conv(flipped, projected)))


class BezierLaneNetHead(LaneHead):
    """BezierLaneNet: forward -> {"logits": (B, Q), "curves": (B, Q, 4, 2)} (+ "seg_logits" (B, 1, h, w) in
    training), Q the width of the map it reads (W / 16 on layer3); curves are control points (x / W, y / H)."""

    # The constructor's parameters with a range, and what a good value of each is: checked by the constructor,
    # and by the config check under model.head.* before any work (one place to say it).
    SETTINGS = {
        "max_lanes": integer(1),
        "channels": integer(1),
        "dilations": int_list(1),
        "dilated_mid_channels": integer(1),
        "projection_layers": integer(0),
        "projection_kernel": integer(1),
        "seg_mid_channels": integer(1),
        "seg_downsample": integer(1),
        "seg_line_width": number(0, low_open=True),
        "num_sample_points": integer(2),
        "match_alpha": number(0, 1),
        "match_window": any_of(one_of("auto"), integer(0)),
        "label_weight": number(0),
        "curve_weight": number(0),
        "seg_weight": number(0),
        "negative_weight": number(0, low_open=True),
        "seg_negative_weight": number(0, low_open=True),
    }

    def __init__(self, in_channels: list[int], in_strides: list[int], image_size: tuple[int, int],
                 max_lanes: int = 4, channels: int = 256, dilations: tuple[int, ...] = (4, 8),
                 dilated_mid_channels: int = 64, projection_layers: int = 2, projection_kernel: int = 3,
                 seg_mid_channels: int = 64, seg_downsample: int = 4, seg_line_width: float = 0.01,
                 num_sample_points: int = 100, match_alpha: float = 0.8, match_window: int | str = AUTO,
                 label_weight: float = 0.1, curve_weight: float = 1.0, seg_weight: float = 0.75,
                 negative_weight: float = 0.4, seg_negative_weight: float = 0.4) -> None:
        check_settings(self.SETTINGS, locals(), "model.head")
        super().__init__(in_channels, in_strides, image_size)
        h, w = self.image_size
        queries = math.ceil(w / self.in_strides[-1])
        if projection_kernel % 2 == 0:
            raise ValueError(f"model.head.projection_kernel: expected an odd integer, got {projection_kernel}")
        if queries < max_lanes:
            raise ValueError(f"BezierLaneNetHead: max_lanes={max_lanes} exceeds the {queries} queries of a {w} px wide "
                             f"input at stride {self.in_strides[-1]}")
        if h // seg_downsample < 1 or w // seg_downsample < 1:
            raise ValueError(f"BezierLaneNetHead: seg_downsample={seg_downsample} leaves no mask of a {w}x{h} input")
        self.max_lanes, self.num_queries = int(max_lanes), queries
        self.seg_downsample, self.seg_line_width = int(seg_downsample), float(seg_line_width)
        self.match_window = resolve_window(match_window, queries, "BezierLaneNetHead: match_window")
        self.num_sample_points, self.match_alpha = int(num_sample_points), match_alpha
        self.weights = {"label": label_weight, "curve": curve_weight, "seg": seg_weight}
        self.negative_weight, self.seg_negative_weight = negative_weight, seg_negative_weight

        c_in = self.in_channels[-1]
        self.reducer = (nn.Identity() if c_in == channels
                        else nn.Sequential(_conv_bn(c_in, channels), nn.ReLU(inplace=True)))
        self.seg_head = nn.Sequential(_conv_bn(channels, seg_mid_channels, 3), nn.ReLU(inplace=True),
                                      nn.Conv2d(seg_mid_channels, 1, 1, bias=False))
        self.dilated_blocks = nn.Sequential(*[DilatedBottleneck(channels, dilated_mid_channels, int(d))
                                              for d in dilations])
        self.fusion = FeatureFlipFusion(channels)
        layers = []
        for _ in range(projection_layers):
            layers += [nn.Conv1d(channels, channels, projection_kernel, padding=projection_kernel // 2),
                       nn.BatchNorm1d(channels), nn.ReLU(inplace=True)]
        self.projection = nn.Sequential(*layers)
        self.proj_classification = nn.Conv1d(channels, 1, 1)
        self.proj_regression = nn.Conv1d(channels, 8, 1)

    # ------------------------------------------------------------------ forward
    def forward(self, features: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        x = self.reducer(features[-1])
        out = {}
        if self.training:  # the auxiliary segmentation: training only
            out["seg_logits"] = self.seg_head(x)
        x = self.dilated_blocks(x)
        if torch.is_autocast_enabled(x.device.type):  # as the official (mmcv's DCN has no fp16): fp32 under autocast
            with torch.autocast(x.device.type, enabled=False):
                x = self.fusion(x.float())
        else:
            x = self.fusion(x)
        x = self.projection(x.mean(dim=2))  # the official AvgPool2d over the whole height -> (B, C, Q)
        b, q = x.shape[0], x.shape[-1]
        out["logits"] = self.proj_classification(x)[:, 0]
        out["curves"] = self.proj_regression(x).permute(0, 2, 1).reshape(b, q, 4, 2)
        return out

    # ------------------------------------------------------------------ targets and loss
    def encode(self, lanes: list[np.ndarray], meta: dict | None = None) -> dict[str, np.ndarray]:
        """GT lanes (input pixels) -> control_points (max_lanes, 4, 2), lane_valid (max_lanes,), seg (h, w)."""
        return encode_targets(lanes, self.image_size, self.max_lanes, self.seg_downsample, self.seg_line_width,
                              self.num_sample_points)

    def loss(self, raw: dict[str, torch.Tensor], targets: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """label_weight x existence BCE + curve_weight x sampled-point L1 + seg_weight x segmentation BCE."""
        cps = targets["control_points"]
        if cps.ndim != 4 or cps.shape[0] != raw["logits"].shape[0] or tuple(cps.shape[2:]) != (4, 2):
            raise ValueError(f"BezierLaneNetHead.loss: targets['control_points'] must be "
                             f"({raw['logits'].shape[0]}, max_lanes, 4, 2), got {tuple(cps.shape)}")
        parts = bezier_losses(raw, targets, self.match_alpha, self.match_window, self.num_sample_points,
                              self.negative_weight, self.seg_negative_weight)
        per_sample = sum(self.weights[k] * v for k, v in parts.items())
        return {"loss": per_sample.mean(), "per_sample": per_sample, "label_loss": parts["label"].mean(),
                "curve_loss": parts["curve"].mean(), "seg_loss": parts["seg"].mean()}

    # ------------------------------------------------------------------ decode
    def decode(self, raw: dict, conf_threshold: float = 0.5, local_maximum_window: int | str = AUTO,
               max_lanes: int | None = None, official_writer: str | None = None, *,
               with_scores: bool = False) -> list[list[np.ndarray]] | list[list[tuple[np.ndarray, float]]]:
        """Per image: the queries whose existence probability exceeds conf_threshold and is the maximum of its
        local_maximum_window queries (0: off; "auto": the official 9 scaled to the query count, as the matching's),
        at most max_lanes of them (None: all), as lanes y descending, left to right. `official_writer` None (ours):
        the most confident kept, each curve read at every pixel row it spans (ROW_TOLERANCE), inside the image;
        "tusimple": the official pruning (the least confident dropped, equal confidences together) and the points
        the official TuSimple writer gives each curve (bezier.official_tusimple_points: the nearest of 720 samples
        in t at its rows 160, 170, ..., 710, x in [0, 1] of the width), in input pixels; "culane": the same
        pruning and the 50 points in t the official CULane writer gives each curve, inside the image or not
        (bezier.official_culane_points). `with_scores`: (lane, score) pairs, the score the query's existence
        probability (the sigmoid of its logit, the value conf_threshold reads)."""
        writers = {"tusimple": (official_tusimple_points, OFFICIAL_TUSIMPLE_SIZE),
                   "culane": (official_culane_points, OFFICIAL_CULANE_SIZE)}
        if official_writer is not None and official_writer not in writers:
            raise ValueError(f"model.decode.official_writer={official_writer!r}: expected null, tusimple or culane")
        prob = raw["logits"].detach().float().sigmoid()
        window = resolve_window(local_maximum_window, prob.shape[1], "decode: local_maximum_window")
        keep = (prob > conf_threshold) & local_maximum(prob, window)
        curves = raw["curves"].detach().double().cpu().numpy()
        h, w = self.image_size
        if official_writer is not None:
            kept = prune_lanes(prob.cpu().numpy(), keep.cpu().numpy(), max_lanes)
            points, (big_h, big_w) = writers[official_writer]
            to_input = np.array([w / big_w, h / big_h])
            out = []
            probs = prob.cpu().numpy()
            for i in range(prob.shape[0]):
                queries = np.flatnonzero(kept[i])
                lanes = [points(curves[i, q]) * to_input for q in queries]
                pairs = [(as_lane(lane), probs[i, q]) for lane, q in zip(lanes, queries) if len(lane)]
                out.append(lanes_with_scores([lane for lane, _ in pairs], [p for _, p in pairs], with_scores))
            return out
        scale = np.array([w, h], dtype=np.float64)
        rows = np.arange(h - 1, -1, -1, dtype=np.float64)
        out = []
        for i in range(prob.shape[0]):
            idx = torch.nonzero(keep[i]).flatten()
            idx = idx[torch.argsort(prob[i, idx], descending=True, stable=True)]
            if max_lanes is not None:
                idx = idx[:max_lanes]
            lanes, lane_scores = [], []
            for q in idx.tolist():
                xs = x_at_rows(curves[i, q] * scale, rows, tolerance=ROW_TOLERANCE)
                ok = np.isfinite(xs) & (xs >= 0) & (xs <= w - 1)
                if ok.sum() >= 2:
                    lanes.append(as_lane(np.stack([xs[ok], rows[ok]], axis=1)))
                    lane_scores.append(prob[i, q].item())
            out.append(lanes_with_scores(lanes, lane_scores, with_scores))
        return out
