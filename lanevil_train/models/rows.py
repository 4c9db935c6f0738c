"""Lanes as x at fixed rows: the row geometry and the target encoding that LaneATT, CLRNet and LaneFormer share
(numpy only, so it runs in data workers). A lane is x at ``n_offsets`` rows from the bottom row (row 0) to the top
row (y = 0).

How a fraction f of the image becomes pixels (FRACTION_SCALES): ``last_pixel`` (this project's own configs)
f x (W - 1) and f x (H - 1), so the bottom row is y = H - 1 and f = 1 the last pixel; ``size`` (the official
LaneATT's, lib/models/laneatt.py l. 36 and 281) f x W and f x H, the bottom row at y = H.
"""

from __future__ import annotations

import numpy as np

from lanevil_train.lanes import as_lane, lane_x_at

UNDEFINED_X = -1e5  # target x on rows where the ground-truth lane does not exist
# A fraction f of the width (height) in pixels: f x (W - 1) ("last_pixel") or f x W ("size", the official's)
FRACTION_SCALES = ("last_pixel", "size")
def pixels_per_unit(size: int, scale: str = "last_pixel") -> float:
    """The pixels a whole image side of `size` pixels spans as a fraction 1 (FRACTION_SCALES)."""
    if scale not in FRACTION_SCALES:
        raise ValueError(f"model.head.fraction_scale={scale!r}: expected one of {', '.join(FRACTION_SCALES)}")
    return float(size - 1 if scale == "last_pixel" else size)


def row_ys(height: int, n_offsets: int, scale: str = "last_pixel") -> np.ndarray:
    """y (pixels) of the n_offsets anchor rows, bottom row first (y = H - 1, or y = H with scale "size"), top
    row (y = 0) last."""
    return np.linspace(pixels_per_unit(height, scale), 0, n_offsets)


def inside_width(xs: np.ndarray, width: int, scale: str = "last_pixel") -> np.ndarray:
    """Which x lie in the image: [0, W - 1] ("last_pixel"), or the official targets' [0, W) ("size",
    lib/datasets/lane_dataset.py l. 155)."""
    return (xs >= 0) & ((xs <= width - 1) if scale == "last_pixel" else (xs < width))


def _extrapolate(p0: np.ndarray, p1: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """x on the straight line through points p0, p1 (distinct y) at rows ys."""
    return p0[0] + (ys - p0[1]) * (p1[0] - p0[0]) / (p1[1] - p0[1])


def encode_lane(lane: np.ndarray, image_size: tuple[int, int], n_offsets: int,
                scale: str = "last_pixel") -> tuple[int, int, np.ndarray] | None:
    """One lane -> (start row, length in rows, x per row); None if it never enters the image.

    As in the official LaneATT, the lane is extended straight down to the image bottom from its
    two lowest points, and ``start`` is the first row (from the bottom) inside the image. It is
    also extended one row up, so the top anchor row at or above the lane's end is covered. The
    rows, and which x are inside the image, follow `scale` (FRACTION_SCALES: row_ys, inside_width).
    """
    h, w = image_size
    lane = as_lane(lane)
    _, first = np.unique(lane[:, 1], return_index=True)
    lane = lane[np.sort(first)]  # drop repeated y, keep y descending
    if len(lane) < 2:
        return None
    ys = row_ys(h, n_offsets, scale)
    ymin, ymax = lane[-1, 1], lane[0, 1]
    strip = ys[0] / (n_offsets - 1)
    xs = np.full(n_offsets, UNDEFINED_X)
    span = (ys >= ymin) & (ys <= ymax)
    xs[span] = lane_x_at(lane, ys[span])
    below = ys > ymax
    xs[below] = _extrapolate(lane[0], lane[1], ys[below])
    above = (ys < ymin) & (ys > ymin - strip)
    xs[above] = _extrapolate(lane[-1], lane[-2], ys[above])
    inside = (xs > UNDEFINED_X / 2) & inside_width(xs, w, scale)
    if not inside.any():
        return None
    start = int(np.argmax(inside))
    end = start
    while end + 1 < n_offsets and inside[end + 1]:
        end += 1
    return start, end - start + 1, xs


