"""GANet's own neck, built inside its head (models/ganet/head.py) from the backbone's maps (C3, C4, C5), as the
official DeformFPN (Wolfwjs/GANet, mmdet/models/necks/dcn_fpn.py) orders it:

1. C5 goes through two self-attention layers, each adding a sine position embedding after its first conv, and
   the result replaces C5 (``trans_mode='replace'``, 512 -> 64 -> 64 channels for ResNet-18);
2. 1x1 lateral convs bring every level to ``channels``; the top-down path adds each coarser lateral, upsampled
   (nearest), to the next finer one;
3. the finest merged lateral goes through the Lane-aware Feature Aggregator (LFA), then a 3x3 conv: the features
   the keypoint heatmap reads. The merged lateral itself (before LFA and conv) is what the start-point offset and
   error branches read (``dcn_only_cls``: the official's ``aux_feat``).

The official's 3x3 output convs of the stride-16 and stride-32 levels feed nothing (its head reads level 0 only):
they are left out here.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from lanevil_train.models.sampling import sample_at

POSITION_TEMPERATURE = 10000.0  # the official PositionEmbeddingSine default (dcn_fpn.py), unnormalised positions


def sine_position_embedding(height: int, width: int, channels: int, temperature: float = POSITION_TEMPERATURE,
                            device=None) -> torch.Tensor:
    """The official (DETR's) sine embedding without normalisation -> (channels, height, width).

    With n = channels / 2 and positions counted from 1 (y = row + 1, x = column + 1): the first n channels encode
    y, the next n x; channel 2i is sin(p / T^(2i / n)) and channel 2i + 1 is cos(p / T^(2i / n))."""
    if channels % 2:
        raise ValueError(f"sine_position_embedding: channels must be even (half for y, half for x), got {channels}")
    n = channels // 2
    k = torch.arange(n, dtype=torch.float32, device=device)
    dim_t = temperature ** (2 * torch.div(k, 2, rounding_mode="floor") / n)  # (n,): pairs share a frequency

    def encode(positions: torch.Tensor) -> torch.Tensor:  # (L,) -> (n, L)
        angle = positions[None, :] / dim_t[:, None]
        return torch.where((k % 2 == 0)[:, None], angle.sin(), angle.cos())

    y = encode(torch.arange(1, height + 1, dtype=torch.float32, device=device))  # (n, H)
    x = encode(torch.arange(1, width + 1, dtype=torch.float32, device=device))  # (n, W)
    return torch.cat([y[:, :, None].expand(n, height, width), x[:, None, :].expand(n, height, width)])


def _conv_bn_relu(c_in: int, c_out: int) -> nn.Sequential:
    """mmcv's ConvModule with BN and ReLU: a 3x3 conv without bias (the norm has one)."""
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, padding=1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU())


class SelfAttention(nn.Module):
    """The official AttentionLayer (dcn_fpn.py): conv-BN-ReLU; plus the position embedding; attention of every
    position over all (query/key at C / ratio channels, softmax over the keys); gamma * attended + the input with
    its positions (gamma starts at 0); conv-BN-ReLU."""

    def __init__(self, c_in: int, c_out: int, ratio: int = 4, positions: bool = True) -> None:
        super().__init__()
        self.positions = positions
        self.pre = _conv_bn_relu(c_in, c_out)
        self.query = nn.Conv2d(c_out, c_out // ratio, 1)
        self.key = nn.Conv2d(c_out, c_out // ratio, 1)
        self.value = nn.Conv2d(c_out, c_out, 1)
        self.gamma = nn.Parameter(torch.zeros(1))
        self.post = _conv_bn_relu(c_out, c_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.pre(x)
        b, c, h, w = x.shape
        if self.positions:
            x = x + sine_position_embedding(h, w, c, device=x.device).to(x.dtype)
        q = self.query(x).flatten(2).transpose(1, 2)  # (B, N, C')
        k = self.key(x).flatten(2)  # (B, C', N)
        attn = torch.softmax(torch.bmm(q, k), dim=-1)  # (B, N, N): each query over the keys
        out = torch.bmm(self.value(x).flatten(2), attn.transpose(1, 2)).reshape(b, c, h, w)
        return self.post(self.gamma * out + x)


def _conv_relu(c_in: int, c_out: int, n: int) -> nn.Sequential:
    return nn.Sequential(*[m for i in range(n) for m in (nn.Conv2d(c_in if i == 0 else c_out, c_out, 3, padding=1),
                                                         nn.ReLU(inplace=True))])


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


class GANetNeck(nn.Module):
    """The official DeformFPN at GANet's setting (``deconv_layer=[True, False, False]``, ``deconv_before=False``,
    ``dcn_only_cls=True``, ``trans_idx=-1``): see the module docstring. ``forward(features, size)`` takes the
    backbone's maps finest first and the finest level's expected (h, w) and returns

    - ``features``: the 3x3 conv of the LFA's output on the finest merged lateral (the heatmap branch's input);
    - ``lateral``: the finest merged lateral (the offset and error branches' input);
    - ``points``: the LFA's points (B, 2K, h, w)."""

    def __init__(self, in_channels: list[int], channels: int, attention_layers: int, attention_ratio: int,
                 lfa_channels: int, lfa_convs: int, lfa_points: int, lfa_gradient_mul: float,
                 attention_channels: int | None = None) -> None:
        super().__init__()
        in_channels = list(in_channels)
        attended = channels if attention_channels is None else attention_channels
        # the official trans_cfg: attn_in_dims [C5, A, ...], attn_out_dims [A, ...], ratio 4, stride 1, where A is
        # the FPN's channels (ResNet-18/34: 64) or its own (ResNet-101: 256, its lateral then 256 -> 64)
        self.attention = nn.Sequential(*[SelfAttention(in_channels[-1] if i == 0 else attended, attended,
                                                       attention_ratio) for i in range(attention_layers)])
        if attention_layers:
            in_channels[-1] = attended  # the attended map replaces C5
        self.lateral = nn.ModuleList(nn.Conv2d(c, channels, 1) for c in in_channels)
        self.lfa = LaneAwareAggregator(channels, lfa_channels, lfa_points, lfa_convs, lfa_gradient_mul)
        self.output = nn.Conv2d(channels, channels, 3, padding=1)
        # the official DeformFPN.init_weights (called by the detector's constructor): xavier-uniform weights and
        # zero biases for every Conv2d of the neck, the attention's and the LFA's included; the LFA's point output
        # keeps its small normal start (see LaneAwareAggregator)
        point_out = self.lfa.point_out[-1]
        for module in self.modules():
            if isinstance(module, nn.Conv2d) and module is not point_out and module is not self.lfa.project:
                nn.init.xavier_uniform_(module.weight)
                if module.bias is not None:
                    nn.init.zeros_(module.bias)

    def forward(self, features: list[torch.Tensor], size: tuple[int, int]) -> dict[str, torch.Tensor]:
        features = list(features)
        features[-1] = self.attention(features[-1])
        merged = [lateral(f) for lateral, f in zip(self.lateral, features)]
        for i in range(len(merged) - 1, 0, -1):  # top-down: coarser upsampled (nearest) and added
            merged[i - 1] = merged[i - 1] + F.interpolate(merged[i], size=merged[i - 1].shape[-2:], mode="nearest")
        # zero-pad then crop to the expected size (a backbone that floors odd sizes); no shape-dependent branch
        hf, wf = size
        lateral = F.pad(merged[0], (0, wf, 0, hf))[:, :, :hf, :wf]
        aggregated, points = self.lfa(lateral)
        return {"features": self.output(aggregated), "lateral": lateral, "points": points}

