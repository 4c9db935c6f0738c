"""Lanes as pixel masks: each lane drawn into its slot of a segmentation target (SCNN's lanes, CLRNet's auxiliary
segmentation), with the line thickness scaled to the input (numpy and OpenCV only, so it runs in data workers)."""

from __future__ import annotations

import cv2
import numpy as np

from lanevil_train.lanes import assign_slots

_SHIFT = 4  # cv2 fixed-point bits: lanes are drawn at 1/16 px precision


def bottom_x(lane: np.ndarray, height: int) -> float:
    """x where the lane, extended straight from its two lowest points, meets the bottom row (y = height - 1)."""
    pts = lane[np.argsort(-lane[:, 1], kind="stable")]
    (x0, y0), (x1, y1) = pts[0], pts[-1]
    for x1_, y1_ in pts[1:]:  # the next point above the lowest one (skip repeated rows)
        if y1_ < y0:
            x1, y1 = x1_, y1_
            break
    if y1 >= y0:  # a horizontal lane: no extension
        return float(x0)
    return float(x0 + (x0 - x1) / (y0 - y1) * (height - 1 - y0))


def draw_width(lane_width: float, reference_width: float, width: int) -> int:
    """The line thickness in input pixels: `lane_width` px at `reference_width`, scaled to `width`."""
    return max(1, round(lane_width * width / reference_width))


def encode_lanes(lanes: list[np.ndarray], image_size: tuple[int, int], max_lanes: int, thickness: int,
                 mode: str = "ego") -> dict[str, np.ndarray]:
    """GT lanes (input pixels) -> {"seg": uint8 (H, W) classes 0..max_lanes, "exist": float32 (max_lanes,)}."""
    h, w = image_size
    lanes = [np.asarray(lane, dtype=np.float64).reshape(-1, 2) for lane in lanes]
    lanes = [lane for lane in lanes if len(lane) >= 2]
    if len(lanes) > max_lanes:
        raise ValueError(f"SCNNHead.encode: {len(lanes)} lanes, but max_lanes={max_lanes}; raise data.max_lanes")
    xs = [bottom_x(lane, h) for lane in lanes]
    order = np.argsort(xs, kind="stable")
    slots = assign_slots([xs[i] for i in order], w, max_lanes, mode)
    seg = np.zeros((h, w), dtype=np.uint8)
    exist = np.zeros(max_lanes, dtype=np.float32)
    for i, slot in zip(order, slots):
        lane = lanes[i]
        lane = lane[np.argsort(-lane[:, 1], kind="stable")]
        far = 8.0 * max(h, w)  # keeps the fixed-point coordinates in int32
        pts = np.round(np.clip(lane, -far, far) * (1 << _SHIFT)).astype(np.int32)
        mask = np.zeros((h, w), dtype=np.uint8)
        cv2.polylines(mask, [pts.reshape(-1, 1, 2)], False, 1, thickness=thickness, lineType=cv2.LINE_8,
                      shift=_SHIFT)
        drawn = mask.astype(bool)
        if drawn.any():
            seg[drawn] = slot + 1
            exist[slot] = 1.0
    return {"seg": seg, "exist": exist}
