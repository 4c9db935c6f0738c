"""CLRNet targets and lane assembly (numpy; the encoder runs in data workers) and its lane NMS.

A ground-truth lane becomes, as in the official ``GenerateLaneLine``: its x at the 72 fixed rows (extended
straight down to the bottom of the image from its two lowest points), the first row inside the image
(``start_y``), the x there (``start_x``), the number of rows inside (``length``) and its mean angle ``theta``
(the mean over its inside points of the angle from the start point, in units of pi). The rows and the
extension are LaneATT's (``laneatt.anchors.encode_lane``: the same sampling, plus one row above the lane's
top so the top evaluation row is covered).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from lanevil_train.models.laneatt.anchors import UNDEFINED_X, encode_lane
from lanevil_train.models.nms import lane_nms

# target row layout: [valid, start_y (fraction of the height), start_x (px), theta (pi units), length (rows), x_0..]
TARGET_META = 5
__all__ = ["TARGET_META", "UNDEFINED_X", "clrnet_nms", "encode_lanes", "lane_theta"]


def lane_theta(xs_inside: np.ndarray, strip: float) -> float:
    """The official lane angle: the mean over the inside points i >= 1 of atan(rise / run) from the first one,
    in units of pi and in (0, 1) (0.5 vertical). strip: the pixel height between two rows."""
    thetas = []
    for i in range(1, len(xs_inside)):
        theta = math.atan(i * strip / (xs_inside[i] - xs_inside[0] + 1e-5)) / math.pi
        thetas.append(theta if theta > 0 else 1 - abs(theta))
    return float(np.mean(thetas)) if thetas else 0.5


def encode_lanes(lanes: list[np.ndarray], image_size: tuple[int, int], n_points: int, max_lanes: int,
                 row_span: float | None = None) -> np.ndarray:
    """Ground-truth lanes (input pixels) -> float32 (max_lanes, TARGET_META + n_points) rows
    [valid, start_y, start_x, theta, length, xs...]; xs are pixels, UNDEFINED_X above the lane. Lanes with fewer
    than two rows inside the image are dropped (the official too); more than max_lanes left is an error.
    `row_span`: the pixels from the bottom row to the top one (default H-1; the official's H, its bottom row one
    pixel below the image, generate_lane_line.py:21-23)."""
    h, w = image_size
    span = h - 1 if row_span is None else row_span
    n_strips = n_points - 1
    strip = span / n_strips
    rows = []
    for lane in lanes:
        # LaneATT's encoder puts its rows from y = height - 1 to 0: a height of span + 1 gives ours
        enc = encode_lane(np.asarray(lane, dtype=np.float64), (span + 1, w), n_points)
        if enc is None or enc[1] < 2:
            continue
        start, length, xs = enc
        theta = lane_theta(xs[start:start + length], strip)
        rows.append((start / n_strips, xs[start], theta, length, xs))
    if len(rows) > max_lanes:
        raise ValueError(f"encode: {len(rows)} lanes inside the {w}x{h} image but max_lanes={max_lanes}; raise the "
                         f"head's max_lanes")
    out = np.zeros((max_lanes, TARGET_META + n_points), dtype=np.float32)
    out[:, TARGET_META:] = UNDEFINED_X
    for i, (start_y, start_x, theta, length, xs) in enumerate(rows):
        out[i, :TARGET_META] = (1.0, start_y, start_x, theta, length)
        out[i, TARGET_META:] = xs
    return out


def start_rows(start_y: torch.Tensor, n_strips: int) -> torch.Tensor:
    """First row of each prediction: start_y x n_strips rounded half up (the official's int(v + 0.5)), clamped."""
    return torch.clamp(torch.floor(start_y * n_strips + 0.5), 0, n_strips).long()


def clrnet_nms(xs: torch.Tensor, start_y: torch.Tensor, length: torch.Tensor, scores: torch.Tensor,
               threshold: float, top_k: int | None, n_strips: int) -> torch.Tensor:
    """CLRNet's NMS (the official CUDA kernel, shared with LaneATT) on its predictions: by descending score, one
    is dropped when its mean |x| distance (pixels, xs (N, S)) to a kept one over the rows both cover is below
    `threshold`. start_y and length are the head's normalised values (fractions of n_strips rows)."""
    return lane_nms(xs, start_rows(start_y, n_strips), length * n_strips, scores, threshold, top_k)
