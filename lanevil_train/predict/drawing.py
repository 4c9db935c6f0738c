"""Predicted lanes drawn over an image: one colour per lane from a fixed palette (lane i, left to right, takes
PALETTE[i % 8]), a line through its points, and its score written beside its bottom point, on the lane's outer
side."""

from __future__ import annotations

from collections.abc import Iterable

import cv2
import numpy as np

# Tableau's ten colours but grey and olive (which a road hides), as BGR: blue, orange, green, red, purple, brown,
# pink, cyan
PALETTE = ((180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148), (75, 86, 140),
           (194, 119, 227), (207, 190, 23))
REFERENCE_WIDTH = 1280  # line widths and text sizes are set for a 1280-px-wide image and scale with the width


def _lane_parts(lane) -> tuple[np.ndarray, float | None]:
    """(points, score) of a PredictedLane, a (points, score) pair or bare points."""
    if hasattr(lane, "points"):
        return np.asarray(lane.points, dtype=np.float64), getattr(lane, "score", None)
    if isinstance(lane, tuple) and len(lane) == 2 and np.ndim(lane[1]) == 0:
        return np.asarray(lane[0], dtype=np.float64), lane[1]
    return np.asarray(lane, dtype=np.float64), None


def draw_lanes(image: np.ndarray, lanes: Iterable, color: str = "bgr", copy: bool = True,
               thickness: int | None = None) -> np.ndarray:
    """`image` (uint8 HxWx3, `color` "bgr" or "rgb") with `lanes` drawn: each a PredictedLane (points (N, 2) in the
    image's pixels and a score), a (points, score) pair or bare points (no score written). Returns a copy unless
    `copy` is False. The line is `thickness` px wide (default 3 px at 1280 px of width, at least 1)."""
    if color not in ("bgr", "rgb"):
        raise ValueError(f"color={color!r}: expected bgr or rgb")
    out = np.array(image, dtype=np.uint8, copy=True) if copy else image
    height, width = out.shape[:2]
    scale = width / REFERENCE_WIDTH
    thickness = thickness or max(1, int(round(3 * scale)))
    font_scale = max(0.35, 0.7 * scale)
    text_thickness = max(1, int(round(2 * scale)))
    for i, lane in enumerate(lanes):
        points, score = _lane_parts(lane)
        points = points.reshape(-1, 2)
        points = points[np.isfinite(points).all(axis=1)]
        if len(points) == 0:
            continue
        colour = PALETTE[i % len(PALETTE)]
        colour = colour[::-1] if color == "rgb" else colour
        pixels = np.round(points).astype(np.int32)
        if len(pixels) == 1:
            cv2.circle(out, tuple(int(v) for v in pixels[0]), thickness, colour, -1, cv2.LINE_AA)
        else:
            cv2.polylines(out, [pixels.reshape(-1, 1, 2)], False, colour, thickness, cv2.LINE_AA)
        if score is None:
            continue
        text = f"{float(score):.2f}"
        (text_w, text_h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, font_scale, text_thickness)
        bottom = pixels[int(np.argmax(pixels[:, 1]))]  # the lane's lowest point in the image
        # on the outer side of the lane (it leans toward the image's centre as it rises), off its line
        x = bottom[0] - text_w - 2 * thickness if bottom[0] < width / 2 else bottom[0] + 2 * thickness
        x = int(np.clip(x, 0, max(0, width - text_w)))
        # above the bottom point, or below it for a lane leaving the image at a side (its line rises from there)
        side = bottom[1] < height - 2 * (text_h + 2 * thickness)
        y = bottom[1] + text_h + 2 * thickness if side else bottom[1] - 2 * thickness
        y = int(np.clip(y, text_h + 1, height - 2))
        cv2.putText(out, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, font_scale, (0, 0, 0), text_thickness + 2,
                    cv2.LINE_AA)  # a dark outline, readable on any road
        cv2.putText(out, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, font_scale, colour, text_thickness, cv2.LINE_AA)
    return out
