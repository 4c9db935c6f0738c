"""Features read at arbitrary points of the input image, by bilinear interpolation (plain torch ``grid_sample``,
so it traces and exports to ONNX at opset 16+). Deformable-style heads (BezierLaneNet's feature flip fusion,
GANet's lane-aware feature aggregator) sample with it.

Points are in input pixels: x in [0, W-1] left to right, y in [0, H-1] top to bottom, where (H, W) is the
network's input size; a feature map of any stride covers the same image, so pixel 0 is its first cell's centre
and pixel W-1 its last (``align_corners=True``). Points outside the image read zeros.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def sample_at(fmap: torch.Tensor, xs: torch.Tensor, ys: torch.Tensor, image_size) -> torch.Tensor:
    """fmap (B, C, h, w) read at points xs, ys (B, *shape) in input pixels -> (B, C, *shape)."""
    if xs.shape != ys.shape or xs.shape[0] != fmap.shape[0]:
        raise ValueError(f"xs {tuple(xs.shape)} and ys {tuple(ys.shape)} must share a shape whose first axis is "
                         f"the batch of fmap {tuple(fmap.shape)}")
    height, width = image_size
    shape = xs.shape[1:]
    gx = xs.reshape(xs.shape[0], 1, -1) * (2.0 / max(width - 1, 1)) - 1.0
    gy = ys.reshape(ys.shape[0], 1, -1) * (2.0 / max(height - 1, 1)) - 1.0
    grid = torch.stack([gx, gy], dim=-1).to(fmap.dtype)  # (B, 1, N, 2)
    values = F.grid_sample(fmap, grid, mode="bilinear", padding_mode="zeros", align_corners=True)  # (B, C, 1, N)
    return values.reshape(fmap.shape[0], fmap.shape[1], *shape)
