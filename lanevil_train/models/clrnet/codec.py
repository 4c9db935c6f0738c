"""CLRNet targets and lane assembly (numpy; the encoder runs in data workers) and its lane NMS.

A ground-truth lane becomes, as in the official ``GenerateLaneLine``: its x at the 72 fixed rows (extended
straight down to the bottom of the image from its two lowest points), the first row inside the image
(``start_y``), the x there (``start_x``), the number of rows inside (``length``) and its mean angle ``theta``
(the mean over its inside points of the angle from the start point, in units of pi). The rows and the
extension are LaneATT's (``laneatt.anchors.encode_lane``: the same sampling, plus one row above the lane's
top so the top evaluation row is covered).

Decoding (``CLRNetHead.decode``) keeps, by default, a lane's points inside the image plus the exact border
crossings (``lanes.row_proposal_to_lane``). ``lane_points: official`` gives instead the points of the official
``Lane`` (``official_rows``, ``official_kept_rows``; the facts in models/clrnet/official.py, "Decoding").
"""

from __future__ import annotations

import math

import numpy as np
import torch

from lanevil_train.models.nms import lane_nms
from lanevil_train.models.rows import UNDEFINED_X, encode_lane

# target row layout: [valid, start_y (fraction of the height), start_x (px), theta (pi units), length (rows), x_0..]
TARGET_META = 5
__all__ = ["TARGET_META", "UNDEFINED_X", "clrnet_nms", "encode_lanes", "lane_theta", "official_kept_rows",
           "official_rows"]


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


def official_rows(start_y: float, length: float, n_strips: int) -> tuple[int, int]:
    """The official decoding's first and last row of a prediction (clr_head.py:477, 288-292 at 7269e9d): the
    length rounded in float32 (``torch.round(length x n_strips)``), the start as Python's ``round(start_y x
    n_strips)`` in double, both half to even; the start clamped to [0, n_strips], the end = start + length - 1
    clamped above at n_strips only (a length below 1 leaves it under the start, even negative)."""
    rows = np.float32(np.float32(length) * np.float32(n_strips))
    length_rows = int(np.rint(rows))
    start = min(max(0, int(np.rint(float(np.float32(start_y)) * n_strips))), n_strips)
    return start, min(start + length_rows - 1, n_strips)


def official_kept_rows(xs: np.ndarray, start: int, end: int, keep_left: bool = False) -> np.ndarray:
    """Which of a prediction's rows (bottom first) the official decoding turns into the Lane's points
    (clr_head.py:296-301 at 7269e9d), xs its x as fractions of the input width: a row with x >= 0 (any x past
    the right edge kept), not after `end` (the rows from end + 1 to the top dropped, counted from the top as a
    Python slice when end + 1 is negative), and, below `start`, only while it and every row up to the start have
    x in [0, 1] (the lane extended down until it first leaves the image; the test reads the rows as they were
    before either rule). `keep_left`: rows with x < 0 kept too, as CLRerNet's decoding keeps every row from the
    (extended) start to the end (hirotomusiker/CLRerNet libs/models/dense_heads/clrernet_head.py:491-502 at 21761ed)."""
    xs = np.asarray(xs)
    below = (xs[:start] >= 0) & (xs[:start] <= 1)
    extended = np.flip(np.cumprod(np.flip(below))).astype(bool)  # inside, and so is every row up to the start
    keep = np.ones(xs.shape, dtype=bool) if keep_left else xs >= 0
    keep[end + 1:] = False
    keep[:start] &= extended
    return keep
