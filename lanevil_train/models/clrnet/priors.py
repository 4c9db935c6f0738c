"""CLRNet lane priors: learnable straight lines given by (start_y, start_x, theta), and their x at fixed rows.

A prior (and every stage's refined line) is a straight line through its start point at angle ``theta``; its
x is read at ``n_points`` fixed rows evenly spaced over the image height, row 0 the bottom row (y = H-1), the
last row the top (y = 0), as the official CLRNet's ``prior_ys`` (72 points). Units are the official's
normalised ones:

- ``start_y``: height of the start point above the bottom row, as a fraction of the height (row / n_strips);
- ``start_x``: x of the start point as a fraction of W-1;
- ``theta``: the line's angle to the x axis (y pointing up) in units of pi: 0.5 is vertical, below 0.5 the
  line leans right as it goes up, above 0.5 left.

The rows span ``row_span`` pixels: by default H-1 (the bottom row on the last pixel row, y = H-1), so a line's x
is exact at our row positions. The official spans ``img_h`` (its bottom row at y = H, one pixel below the image:
``prior_ys`` x img_h, clr_head.py:136-139 and 245-249; GenerateLaneLine's ``offsets_ys``, generate_lane_line.py:21-23);
the head's ``row_span: height`` computes that, as the official weights need (models/clrnet/official.py).
"""

from __future__ import annotations

import math

import torch


def init_prior_embeddings(num_priors: int) -> torch.Tensor:
    """The official initial priors (num_priors, 3) [start_y, start_x, theta].

    An eighth start on the left border and an eighth on the right one (pairs of angles 0.16 / 0.32 on the left,
    0.68 / 0.84 on the right, start heights evenly spread over the lower half), three quarters on the bottom
    border (groups of four angles 0.2, 0.4, 0.6, 0.8 at evenly spaced x), as in the paper's 192 priors.
    """
    if num_priors < 32:
        raise ValueError(f"num_priors must be >= 32 (an eighth on each side border, in at least two pairs), "
                         f"got {num_priors}")
    out = torch.zeros(num_priors, 3)
    n_side = num_priors // 8
    n_bottom = num_priors * 3 // 4
    side_step = 0.5 / (n_side // 2 - 1)
    bottom_step = 1.0 / (n_bottom // 4 + 1)
    for i in range(n_side):  # left border
        out[i] = torch.tensor([(i // 2) * side_step, 0.0, 0.16 if i % 2 == 0 else 0.32])
    for i in range(n_side, n_side + n_bottom):  # bottom border
        out[i] = torch.tensor([0.0, ((i - n_side) // 4 + 1) * bottom_step, 0.2 * (i % 4 + 1)])
    for i in range(n_side + n_bottom, num_priors):  # right border
        out[i] = torch.tensor([((i - n_side - n_bottom) // 2) * side_step, 1.0, 0.68 if i % 2 == 0 else 0.84])
    return out


def row_fractions(n_points: int) -> torch.Tensor:
    """Height of each of the n_points rows above the bottom row, as a fraction of the height: 0 ... 1."""
    return torch.linspace(0.0, 1.0, n_points)


def row_ys(height: int, n_points: int, row_span: float | None = None) -> torch.Tensor:
    """y (pixels) of the rows, bottom row (y = row_span, default H-1) first, top row (0) last."""
    return (height - 1 if row_span is None else row_span) * (1.0 - row_fractions(n_points))


def line_xs(lines: torch.Tensor, fractions: torch.Tensor, image_size: tuple[int, int],
            row_span: float | None = None) -> torch.Tensor:
    """x of each straight line (..., 3) [start_y, start_x, theta] at the rows `fractions` (S,), as a fraction of
    W-1: shape (..., S). `row_span`: the pixels from the bottom row to the top one (default H-1; the official's
    H). The 1e-5 keeps tan away from 0 at theta = 0 or 1, as the official."""
    h, w = image_size
    span = h - 1 if row_span is None else row_span
    start_y, start_x, theta = lines[..., 0:1], lines[..., 1:2], lines[..., 2:3]
    rise = (fractions - start_y) * span  # pixels above the start point
    return start_x + rise / torch.tan(theta * math.pi + 1e-5) / (w - 1)


def sample_indices(n_points: int, sample_points: int) -> torch.Tensor:
    """The rows (of n_points, row 0 the bottom) at which ROI features are sampled, in the order the features are
    laid out: sample_points rows evenly spread (floor of linspace(0, 1) x (n_points - 1)), TOP FIRST.

    The official chooses the rows bottom first (``sample_x_indexs``) and then flips both the sampled y
    (``prior_feat_ys``) and the prior xs before grid_sample, so feature 0 is the top row; the (9, 1) convolutions
    and the fc layer over the flattened points see that order (and official weights expect it)."""
    if not 2 <= sample_points <= n_points:
        raise ValueError(f"sample_points must be in [2, num_points={n_points}], got {sample_points}")
    return (torch.linspace(0.0, 1.0, sample_points) * (n_points - 1)).long().flip(0)
