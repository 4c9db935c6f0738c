"""Pieces the official-weights tests share when they write an official network from the facts of its code."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class ConvModule(nn.Module):
    """mmcv's ConvModule as the official configs build it (CLRNet, GANet): `conv` (biased unless normed), then `bn`
    and a ReLU where asked."""

    def __init__(self, cin, cout, kernel, padding=0, norm=False, act=False):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, kernel, padding=padding, bias=not norm)
        if norm:
            self.bn = nn.BatchNorm2d(cout)
        self.act = act

    def forward(self, x):
        x = self.conv(x)
        if hasattr(self, "bn"):
            x = self.bn(x)
        return F.relu(x) if self.act else x


def randomise_batch_norm(m: nn.Module) -> None:
    """A BatchNorm layer's weights and running statistics away from their initial values (a trained file's), so a
    statistic left unloaded or read in the wrong order shows in the outputs."""
    nn.init.uniform_(m.weight, 0.5, 1.5)
    nn.init.normal_(m.bias, 0.0, 0.1)
    m.running_mean.normal_(0.0, 0.1)
    m.running_var.uniform_(0.5, 2.0)
    m.num_batches_tracked.fill_(1234)


def ufld_culane_file_keys() -> dict:
    """The keys (placeholder values, the shapes that tell the release) of a UFLD v1 CULane ResNet-18 file: a file of
    another family for the refusal tests."""
    return {"model.conv1.weight": torch.zeros(1), "pool.weight": torch.zeros(1), "cls.0.weight": torch.zeros(1),
            "cls.2.weight": torch.zeros(201 * 18 * 4, 1),
            **{f"model.layer{i}.{b}.conv1.weight": torch.zeros(1) for i in range(1, 5) for b in (0, 1)}}
