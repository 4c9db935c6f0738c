"""SCNN's targets and post-processing: lanes <-> per-pixel lane classes (Pan et al., AAAI 2018).

Targets (``encode_lanes``): each lane is drawn as a thick polyline into a class map at the network's
input size, class ``1 + slot`` for the lane in slot ``slot`` (0 is background), plus an existence
vector (1 where a slot's lane drew at least one pixel). CULane's labels (``laneseg_label_w16``) are
lines 16 px wide on its 1640x590 images; the width here is ``lane_width`` px at ``reference_width``
and scales with the input width (16 px at 1640 is about 8 px at SCNN's 800 px input), at least 1 px.
Where lanes overlap (near the vanishing point) the one drawn later, further right, wins.

Slots (``lanes.assign_slots``, shared with UFLD): CULane's label generator sorts the lanes by the x where their linear
fit meets the bottom row, splits them into the lanes left and right of the ego vehicle (where the sign of
their slope changes, else at the image centre) and gives the two
nearest left lanes slots 1, 2 and the two nearest right ones slots 3, 4 (0-based here: 0..3), so a slot
means a position relative to the car ("ego left", "ego right", ...), and lanes beyond those four are
dropped. Here ("ego", the default): the split is the image centre column, the left half of the slots
(max_lanes // 2) holds the left lanes counted outwards from the centre, the rest the right lanes; a side
with more lanes than its slots spills into the other side's free slots (keeping the left-to-right order)
instead of dropping them, so every labelled lane up to max_lanes is learnt. "packed" fills slots 0, 1,
... left to right (the slot is then the lane's rank, which depends on how many lanes lie to its left; on
simulated scenes it trained worse: 87.8 % against 91.7 % TuSimple accuracy after the same 1,000 steps).

Post-processing (``lane_points``): SCNN's prob2lines takes each lane whose existence probability is
above 0.5, samples rows every 20 px of the 590 px CULane image from the bottom, and on each row takes
the argmax column of that lane's probability map when its value is above 0.3; a lane needs at least
2 such points. Here the rows are every ``row_step`` input pixels (the evaluation interpolates between
them), and the column is refined to sub-pixel precision: the probability-weighted mean column of the
run of columns around the row's argmax whose probability is at least half the peak (the argmax of a
flat-topped band is its left edge, and a lane crossing rows at a shallow angle covers a long run of
columns; the official tools blur the map before the argmax for the first reason).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

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


def lane_points(lane_probs: torch.Tensor, exist: torch.Tensor, exist_threshold: float, prob_threshold: float,
                row_step: int, min_points: int) -> list[list[np.ndarray]]:
    """Probability maps (B, L, H, W) and existence probabilities (B, L) -> per image, lanes as (N, 2) float64
    arrays of (x, y) input pixels, y descending (bottom first), sorted left to right by their bottom x."""
    b, n_lanes, h, w = lane_probs.shape
    rows = torch.arange(h - 1, -1, -row_step, device=lane_probs.device)
    p = lane_probs[:, :, rows, :]  # (B, L, R, W)
    peak, arg = p.max(dim=-1, keepdim=True)
    cols = torch.arange(w, device=p.device)
    low = p < peak / 2  # the run around the argmax: columns at half the peak or more
    left = torch.where(low & (cols < arg), cols, -1).amax(-1, keepdim=True)
    right = torch.where(low & (cols > arg), cols, w).amin(-1, keepdim=True)
    weight = p * ((cols > left) & (cols < right)).to(p.dtype)
    x = (weight * cols.to(p.dtype)).sum(-1) / weight.sum(-1).clamp_min(1e-12)
    peak = peak[..., 0]
    hit = (peak > prob_threshold) & (exist[:, :, None] > exist_threshold)
    xs, hit, ys = x.cpu().numpy().astype(np.float64), hit.cpu().numpy(), rows.cpu().numpy().astype(np.float64)
    out = []
    for i in range(b):
        lanes = []
        for k in range(n_lanes):
            keep = hit[i, k]
            if keep.sum() >= max(min_points, 2):
                lanes.append(np.stack([xs[i, k, keep], ys[keep]], axis=1))  # rows already bottom first
        lanes.sort(key=lambda lane: lane[0, 0])
        out.append(lanes)
    return out
