"""Necks: optional modules between the backbone's feature maps and the head (``model.neck``).

A neck is built as ``Neck(in_channels=[...], in_strides=[...], **its config)`` and has ``channels`` and
``strides`` of the maps it returns, in the same order as its input (coarsest last), so the head is built
from them exactly as it would be from a backbone's.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class FPN(nn.Module):
    """Feature pyramid network (Lin et al., CVPR 2017): 1x1 lateral convolutions, a top-down pathway (nearest
    upsampling of the coarser map, added), a 3x3 convolution on each merged map; every output has
    `out_channels` channels. `num_outs` > the input count adds stride-2 3x3 convolutions on the coarsest map."""

    def __init__(self, in_channels, in_strides, out_channels: int = 64, num_outs: int | None = None) -> None:
        super().__init__()
        in_channels, in_strides = list(in_channels), list(in_strides)
        if len(in_channels) != len(in_strides) or not in_channels:
            raise ValueError(f"FPN: in_channels {in_channels} and in_strides {in_strides} must be non-empty lists "
                             f"of the same length")
        if int(out_channels) < 1:
            raise ValueError(f"FPN: out_channels must be a positive integer, got {out_channels!r}")
        num_outs = len(in_channels) if num_outs is None else int(num_outs)
        if num_outs < len(in_channels):
            raise ValueError(f"FPN: num_outs={num_outs} is fewer than its {len(in_channels)} inputs")
        self.lateral = nn.ModuleList(nn.Conv2d(c, out_channels, 1) for c in in_channels)
        self.output = nn.ModuleList(nn.Conv2d(out_channels, out_channels, 3, padding=1) for _ in in_channels)
        self.extra = nn.ModuleList(nn.Conv2d(out_channels, out_channels, 3, stride=2, padding=1)
                                   for _ in range(num_outs - len(in_channels)))
        self.channels = [int(out_channels)] * num_outs
        self.strides = in_strides + [in_strides[-1] * 2 ** (k + 1) for k in range(len(self.extra))]
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.xavier_uniform_(module.weight)
                nn.init.zeros_(module.bias)

    def forward(self, features: list[torch.Tensor]) -> list[torch.Tensor]:
        merged = [lateral(f) for lateral, f in zip(self.lateral, features)]
        for i in range(len(merged) - 1, 0, -1):
            merged[i - 1] = merged[i - 1] + F.interpolate(merged[i], size=merged[i - 1].shape[-2:], mode="nearest")
        outs = [conv(m) for conv, m in zip(self.output, merged)]
        for conv in self.extra:
            outs.append(conv(outs[-1]))
        return outs
