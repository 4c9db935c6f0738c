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

Post-processing, this project's (``lane_points``, ``decode(official_writer=None)``): each slot whose existence
probability is above the threshold, on every ``row_step``-th input row from the bottom, gives a point where the
slot's probability peak on the row is above the threshold; its column is refined to sub-pixel precision: the
probability-weighted mean column of the run of columns around the row's argmax whose probability is at least half
the peak (the argmax of a flat-topped band is its left edge, and a lane crossing rows at a shallow angle covers a
long run of columns); a lane needs ``min_points`` points.

Post-processing, pytorch-auto-drive's (``official_lane_points``, ``decode(official_writer="tusimple" | "culane",
blur=9, max_lanes=...)``, the official_scnn_* experiments), from voldemortX/pytorch-auto-drive at 137e63a
(utils/lane_det_utils.py):

- l. 100-101: the stride-8 logits upsampled bilinearly (align_corners=True) to the input size, softmax over the
  classes (the head's forward and decode); l. 102-103: a slot exists where sigmoid(existence logit) > 0.5;
  l. 104-105 and utils/models/lane_detection/utils.py l. 4-14 (``lane_pruning``): while an image has more than
  ``max_lane`` (the test dict: TuSimple 5, CULane 4) existing slots, every slot at its lowest confidence is dropped
  (ties together; ``prune_lanes``);
- l. 76-78: an existing slot's probability map (float32) is box-blurred, ``cv2.blur(map, (9, 9),
  borderType=cv2.BORDER_REPLICATE)`` (``box_blur``);
- l. 30-36 (``get_lane``): ``ppl`` rows, ``gap`` px apart in the config's ``original_size`` (H, W); on the map of
  height h, row i is ``int(h - (ppl - i) * gap / H * h)`` on TuSimple (ppl=56, gap=10, (720, 1280): 80 + 5 i of 360
  except i = 12, which the float arithmetic puts at 139) and ``int(h - i * gap / H * h - 1)`` on CULane (ppl=18,
  gap=20, (590, 1640): 287, 277, ... of 288), the loop stopping at a negative row (l. 37-38) (``official_rows``);
- l. 39-42: the row's first argmax column ``id`` gives the point ``x = int(id / w * W)`` where the blurred map's
  value there is above ``thresh`` (0.3), else 0; l. 43-44 and 80-81: x = 0 is no point (``coords > 0``), a lane
  needs 2 points;
- l. 82-86: the point's y is the written row: TuSimple ``H - (ppl - i) * gap`` (160, 170, ..., 710: every row
  written, -2 where no point), CULane ``H - i * gap - 1`` (589, 569, ..., 249: the points only, bottom first);
  utils/runners/lane_det_tester.py l. 59-78 writes them (CULane ``"{} {}".format(x, y)`` per point, x a float of
  whole pixels; TuSimple the x per h_sample, -2 where none).

Here the points are returned in input pixels (x * w / W, y * h / H) so that the proportional resize to the
original image (LaneDetector.decode_lanes, no crop) gives the official values again; the TuSimple file reads them
with ``model.row_sampling: points`` (a value only at a lane's own rows, -2 at the others).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch


def box_blur(prob_maps: np.ndarray, size: int) -> np.ndarray:
    """Each (h, w) map of ``prob_maps`` (..., h, w) blurred by the mean of its size x size neighbourhood, the
    border replicated (OpenCV's normalised box filter, as the official decoding); size <= 1: unchanged."""
    if size <= 1:
        return prob_maps
    maps = np.ascontiguousarray(prob_maps, dtype=np.float32)
    flat = maps.reshape(-1, *maps.shape[-2:])
    blurred = [cv2.blur(m, (size, size), borderType=cv2.BORDER_REPLICATE) for m in flat]
    return np.stack(blurred).reshape(maps.shape) if blurred else maps


@dataclass(frozen=True)
class OfficialWriter:
    """The rows pytorch-auto-drive's get_lane reads and writes (see the module docstring)."""

    size: tuple[int, int]  # (H, W): the test config's original_size, the image the points are written in
    gap: int               # px between rows in that image
    points: int            # ppl: rows per lane
    from_bottom: bool      # CULane: rows from the bottom row up; TuSimple: the last one gap px above the bottom


OFFICIAL_WRITERS = {
    # configs/lane_detection/scnn/vgg16_tusimple.py l. 44-50 (test: gap=10, ppl=56, original_size=(720, 1280))
    "tusimple": OfficialWriter(size=(720, 1280), gap=10, points=56, from_bottom=False),
    # configs/lane_detection/scnn/vgg16_culane.py l. 45-51 (test: gap=20, ppl=18, original_size=(590, 1640))
    "culane": OfficialWriter(size=(590, 1640), gap=20, points=18, from_bottom=True),
}


def official_rows(writer: OfficialWriter, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(the map rows read, int; the rows written, in the writer's image) for a map of `height` rows, computed in
    the official's float arithmetic (get_lane l. 30-38: the loop stops at a negative row)."""
    big_h, gap, ppl = writer.size[0], writer.gap, writer.points
    read, written = [], []
    for i in range(ppl):
        if writer.from_bottom:
            row, y = int(height - i * gap / big_h * height - 1), big_h - i * gap - 1
        else:
            row, y = int(height - (ppl - i) * gap / big_h * height), big_h - (ppl - i) * gap
        if row < 0:
            break
        read.append(row)
        written.append(y)
    return np.asarray(read, dtype=np.int64), np.asarray(written, dtype=np.float64)


def official_lane_points(prob_maps: np.ndarray, present: np.ndarray, writer: OfficialWriter, prob_threshold: float,
                         blur: int, min_points: int, with_slots: bool = False) -> list[list]:
    """Probability maps (B, L, h, w) float32 and present slots (B, L) -> per image, the official decoding's lanes as
    (N, 2) arrays of (x, y) input pixels, bottom first, sorted left to right by their bottom x (module docstring).
    `with_slots`: (lane, slot) pairs in the same order, slot the lane's index in L."""
    _, _, h, w = prob_maps.shape
    big_h, big_w = writer.size
    rows, ys = official_rows(writer, h)
    out = []
    for maps, keep in zip(prob_maps, present):
        lanes = []
        for k in np.flatnonzero(keep):
            lines = box_blur(maps[k], blur)[rows]  # (R, w)
            cols = lines.argmax(axis=1)  # the first maximum, as np.argmax per row
            peaks = lines[np.arange(len(rows)), cols]
            xs = np.where(peaks > prob_threshold, np.trunc(cols / w * big_w), 0.0)  # int(id / w * W), >= 0
            valid = xs > 0
            if valid.sum() >= max(int(min_points), 1):
                lane = np.stack([xs[valid] * (w / big_w), ys[valid] * (h / big_h)], axis=1)
                lanes.append((lane[np.argsort(-lane[:, 1], kind="stable")], int(k)))
        lanes.sort(key=lambda pair: pair[0][0, 0])
        out.append(lanes if with_slots else [lane for lane, _ in lanes])
    return out


def lane_points(lane_probs: torch.Tensor, present: torch.Tensor, prob_threshold: float, row_step: int,
                min_points: int, with_slots: bool = False) -> list[list]:
    """Probability maps (B, L, H, W) and the slots to decode (B, L) bool -> per image, lanes as (N, 2) float64
    arrays of (x, y) input pixels, y descending (bottom first), sorted left to right by their bottom x.
    `with_slots`: (lane, slot) pairs in the same order, slot the lane's index in L."""
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
    hit = (peak > prob_threshold) & present.to(peak.device)[:, :, None]
    xs, hit, ys = x.cpu().numpy().astype(np.float64), hit.cpu().numpy(), rows.cpu().numpy().astype(np.float64)
    out = []
    for i in range(b):
        lanes = []
        for k in range(n_lanes):
            keep = hit[i, k]
            if keep.sum() >= max(min_points, 2):
                lanes.append((np.stack([xs[i, k, keep], ys[keep]], axis=1), k))  # rows already bottom first
        lanes.sort(key=lambda pair: pair[0][0, 0])
        out.append(lanes if with_slots else [lane for lane, _ in lanes])
    return out
