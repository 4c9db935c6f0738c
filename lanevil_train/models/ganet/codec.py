"""GANet targets and lane assembly (numpy; the encoder runs in data workers).

Units: the heatmap has one cell per ``stride`` input pixels (the stride-8 FPN level in the paper); a point of the
image at pixel (x, y) is at heatmap coordinates (x / stride, y / stride), in cell (floor(x / s), floor(y / s)),
as in the official ``CollectLanePoints``. Decoded points go back to pixels as (cell + error) * stride.

Targets of one image, as the official:

- keypoints: ``points_per_lane`` points evenly spaced in y over each lane's vertical extent (the official
  samples int(360 / stride) = 45 at stride 8, fitting a cubic spline to the annotation; here the lane is
  interpolated linearly, lanes.lane_x_at), keeping those inside the image;
- ``heatmap`` (1, h, w): a Gaussian of radius ``radius`` (CenterNet's ``draw_umich_gaussian``: diameter 2r + 1,
  sigma = diameter / 6, peak 1) at each keypoint's cell, the maximum where they overlap;
- ``error`` (2, h, w): the keypoint's sub-cell position (x/s - cx, y/s - cy) at its cell (the "compensation");
- ``offsets`` (2, h, w): the vector from the keypoint to its lane's start point (its lowest keypoint inside the
  image), in heatmap cells, at its cell: the global association;
  where keypoints share a cell the last one written sets error and offsets; the official writes bottom to top,
  so a lane's bottom cell ends up with a point above the start; here the start point is written again last, so both
  end points keep their cells and the decoded lane spans the whole lane;
- ``mask`` (1, h, w): 1 at keypoint cells (where error and offsets are supervised);
- ``lfa_points`` (max_lanes, G, 2) and ``lfa_valid`` (max_lanes,): G points along each lane in feature-map index
  units (x / s - 0.5: index j is cell j's centre, as grid_sample reads it), the targets the LFA's auxiliary loss
  pulls its sampling points onto (the official ``lane_points_l0``, 41 points, rounded there to integer cells).

Decoding, as the official ``ktdet_decode_fast`` + ``group_points_fast`` (by centre): keypoints are local maxima
of the heatmap along its rows (a 1 x 3 max pool) above ``kpt_threshold``; each lands at (cell + error) and
predicts its start point at (cell + error + offset); keypoints whose predicted y offset to the start is below
``root_threshold`` are start candidates; their predicted start points (the official: their cells) are grouped
greedily (a candidate joins the first group holding one within ``cluster_threshold`` cells; the head scales the
official 5 cells at 800 px to the input width) and averaged into lane centres; every keypoint joins the nearest
centre within ``cluster_threshold`` of its predicted start (the official takes the first one in its list), others
are dropped; a group with fewer than ``min_points`` keypoints is dropped (the official: more than points_thr = 10).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from lanevil_train.lanes import as_lane, lane_x_at


def heatmap_size(image_size: tuple[int, int], stride: int) -> tuple[int, int]:
    """(h, w) of the stride-`stride` map of an input of this size (ResNet's: ceil)."""
    return math.ceil(image_size[0] / stride), math.ceil(image_size[1] / stride)


def gaussian_kernel(radius: int) -> np.ndarray:
    """CenterNet's (2r + 1)^2 Gaussian, sigma = (2r + 1) / 6, 1 at the centre."""
    diameter = 2 * radius + 1
    sigma = diameter / 6.0
    d = np.arange(-radius, radius + 1, dtype=np.float64)
    g = np.exp(-(d[None, :] ** 2 + d[:, None] ** 2) / (2 * sigma * sigma))
    g[g < np.finfo(g.dtype).eps * g.max()] = 0
    return g


def draw_gaussian(heatmap: np.ndarray, cx: int, cy: int, kernel: np.ndarray) -> None:
    """heatmap = max(heatmap, kernel centred at cell (cx, cy)), clipped at the borders (in place)."""
    r = kernel.shape[0] // 2
    h, w = heatmap.shape
    left, right = min(cx, r), min(w - cx, r + 1)
    top, bottom = min(cy, r), min(h - cy, r + 1)
    if left + right <= 0 or top + bottom <= 0:
        return
    patch = heatmap[cy - top:cy + bottom, cx - left:cx + right]
    np.maximum(patch, kernel[r - top:r + bottom, r - left:r + right], out=patch)


def lane_keypoints(lane: np.ndarray, image_size: tuple[int, int], n: int) -> np.ndarray | None:
    """n points evenly spaced in y from the lane's bottom to its top (within the image rows), those inside the
    image, bottom first, in pixels (K, 2); None if fewer than two."""
    h, w = image_size
    lane = as_lane(lane)
    y_lo, y_hi = max(lane[:, 1].min(), 0.0), min(lane[:, 1].max(), h - 1.0)
    if len(lane) < 2 or y_hi <= y_lo:
        return None
    ys = np.linspace(y_hi, y_lo, n)
    xs = lane_x_at(lane, ys)
    inside = (xs >= 0) & (xs <= w - 1)
    if inside.sum() < 2:
        return None
    return np.stack([xs[inside], ys[inside]], axis=1)


def encode_targets(lanes: list[np.ndarray], image_size: tuple[int, int], stride: int, max_lanes: int,
                   points_per_lane: int = 45, radius: int = 2, lfa_gt_points: int = 41) -> dict[str, np.ndarray]:
    """Ground-truth lanes (input pixels) -> the targets of the module docstring. More than max_lanes lanes
    inside the image is an error."""
    hf, wf = heatmap_size(image_size, stride)
    heatmap = np.zeros((1, hf, wf), np.float32)
    error = np.zeros((2, hf, wf), np.float32)
    offsets = np.zeros((2, hf, wf), np.float32)
    mask = np.zeros((1, hf, wf), np.float32)
    lfa_points = np.zeros((max_lanes, lfa_gt_points, 2), np.float32)
    lfa_valid = np.zeros((max_lanes,), np.float32)
    kernel = gaussian_kernel(radius)
    kept = [k for k in (lane_keypoints(np.asarray(lane, np.float64), image_size, points_per_lane) for lane in lanes)
            if k is not None]
    if len(kept) > max_lanes:
        raise ValueError(f"encode: {len(kept)} lanes inside the {image_size[1]}x{image_size[0]} image but "
                         f"max_lanes={max_lanes}; raise the head's max_lanes")
    for slot, pts in enumerate(kept):
        p = pts / stride  # heatmap coordinates
        start = p[0]
        cells = np.floor(p).astype(np.int64)
        cells[:, 0] = np.clip(cells[:, 0], 0, wf - 1)
        cells[:, 1] = np.clip(cells[:, 1], 0, hf - 1)
        # bottom to top, then the start point again: where several keypoints share a cell the last one written
        # is its target, so the lane's two end points keep their cells and the decoded lane spans the whole lane
        for i in [*range(len(p)), 0]:
            (cx, cy), q = cells[i], p[i]
            draw_gaussian(heatmap[0], cx, cy, kernel)
            error[:, cy, cx] = q - (cx, cy)
            offsets[:, cy, cx] = start - q
            mask[0, cy, cx] = 1.0
        # the LFA targets: lfa_gt_points along the inside part, in feature index units
        ys = np.linspace(pts[0, 1], pts[-1, 1], lfa_gt_points)
        xs = np.interp(ys, pts[::-1, 1], pts[::-1, 0])
        lfa_points[slot, :, 0] = np.clip(xs / stride - 0.5, 0, wf - 1)
        lfa_points[slot, :, 1] = np.clip(ys / stride - 0.5, 0, hf - 1)
        lfa_valid[slot] = 1.0
    return {"heatmap": heatmap, "error": error, "offsets": offsets, "mask": mask, "lfa_points": lfa_points,
            "lfa_valid": lfa_valid}


def row_peaks(heatmap: torch.Tensor) -> torch.Tensor:
    """The official keypoint NMS: True where a cell is the maximum of itself and its left and right neighbours
    (a 1 x 3 max pool over the (B, 1, h, w) heatmap)."""
    return F.max_pool2d(heatmap, (1, 3), stride=1, padding=(0, 1)) == heatmap


def _greedy_groups(points: np.ndarray, threshold: float) -> list[list[int]]:
    """The official start-point grouping: each point joins the first group with a member within threshold."""
    groups: list[list[int]] = []
    for i, p in enumerate(points):
        for group in groups:
            if np.min(np.hypot(*(points[group] - p).T)) <= threshold:
                group.append(i)
                break
        else:
            groups.append([i])
    return groups


def group_keypoints(points: np.ndarray, roots: np.ndarray, is_start: np.ndarray, cluster_threshold: float,
                    with_seeds: bool = False) -> tuple:
    """Keypoints (N, 2), their predicted start points (N, 2) and which are start candidates (N,) -> the keypoint
    indices of each lane, and the lane centres (L, 2): the start candidates' predicted starts grouped greedily and
    averaged; each keypoint joins the nearest centre within cluster_threshold of its predicted start.
    `with_seeds`: also (L,) the keypoint index of each group's first start candidate, the one that founded it."""
    starts = np.flatnonzero(is_start)
    groups = _greedy_groups(roots[starts], cluster_threshold)
    if not groups:
        return ([], np.zeros((0, 2)), np.zeros(0, np.int64)) if with_seeds else ([], np.zeros((0, 2)))
    centres = np.stack([roots[starts[g]].mean(axis=0) for g in groups])
    dist = np.hypot(roots[:, None, 0] - centres[None, :, 0], roots[:, None, 1] - centres[None, :, 1])
    nearest = dist.argmin(axis=1)
    ok = dist[np.arange(len(roots)), nearest] <= cluster_threshold
    members = [np.flatnonzero(ok & (nearest == k)) for k in range(len(centres))]
    if with_seeds:
        return members, centres, np.array([starts[g[0]] for g in groups], dtype=np.int64)
    return members, centres


def assemble_lane(points_px: np.ndarray, image_size: tuple[int, int]) -> np.ndarray | None:
    """Keypoints of one lane (pixels) -> a lane: those inside the image, one point per distinct y (x averaged),
    y descending; None if fewer than two."""
    h, w = image_size
    inside = (points_px[:, 0] >= 0) & (points_px[:, 0] <= w - 1) & (points_px[:, 1] >= 0) & (points_px[:, 1] <= h - 1)
    pts = points_px[inside]
    if len(pts) < 2:
        return None
    ys, inverse = np.unique(pts[:, 1], return_inverse=True)
    if len(ys) < 2:
        return None
    xs = np.bincount(inverse, weights=pts[:, 0]) / np.bincount(inverse)
    return as_lane(np.stack([xs, ys], axis=1))


def decode_lanes(heatmap: torch.Tensor, offsets: torch.Tensor, error: torch.Tensor, stride: int,
                 image_size: tuple[int, int], kpt_threshold: float, root_threshold: float, cluster_threshold: float,
                 min_points: int, with_scores: bool = False) -> list[list]:
    """Raw maps (B, 1, h, w), (B, 2, h, w), (B, 2, h, w) -> per image, lanes in input pixels, left to right.

    `with_scores`: (lane, score) pairs in the same order, the score the heatmap value of the lane's start keypoint:
    of the start candidates whose grouped start points made the lane, the first (the keypoints are taken strongest
    first, so the strongest), the one that founded its group. Its value passed kpt_threshold, as every keypoint's;
    a lane exists because it did."""
    heatmap = heatmap.detach().float()
    keep = row_peaks(heatmap) & (heatmap > kpt_threshold)
    out = []
    for b in range(heatmap.shape[0]):
        iy, ix = (v.cpu().numpy() for v in torch.nonzero(keep[b, 0], as_tuple=True))
        order = np.argsort(-heatmap[b, 0, iy, ix].cpu().numpy(), kind="stable")  # strongest first
        iy, ix = iy[order], ix[order]
        err = error[b].detach().float().cpu().numpy()[:, iy, ix].T
        off = offsets[b].detach().float().cpu().numpy()[:, iy, ix].T
        values = heatmap[b, 0, iy, ix].cpu().numpy()  # each keypoint's heatmap value, strongest first
        points = np.stack([ix, iy], axis=1) + err
        roots = points + off
        groups, _, seeds = group_keypoints(points, roots, off[:, 1] < root_threshold, cluster_threshold,
                                           with_seeds=True)
        lanes = []
        for index, seed in zip(groups, seeds):
            if len(index) < min_points:
                continue
            lane = assemble_lane(points[index].astype(np.float64) * stride, image_size)
            if lane is not None:
                lanes.append((lane, float(min(max(values[seed], 0.0), 1.0))))
        lanes.sort(key=lambda pair: pair[0][0, 0])
        out.append(lanes if with_scores else [lane for lane, _ in lanes])
    return out
