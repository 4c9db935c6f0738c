"""BezierLaneNet targets, Hungarian matching and loss (the official ``HungarianBezierLoss``), and the local-maximum
window over the 1-D query sequence that both the matching and the decoding use.

Targets of one image (``encode_targets``, numpy, run in data workers):
- ``control_points`` (max_lanes, 4, 2) float32: a cubic Bezier curve fitted to each lane (bezier.fit_bezier, at
  chord-length parameters) in coordinates normalised by the input size (x / W, y / H, as the official), then cut
  to its in-image part: 100 points are sampled on it and the curve is restricted to the t span from the first to
  the last point strictly inside (0, 1) x (0, 1) (the official ``cubic_bezier_curve_segment``, which it applies in
  the loss; here once, in the encoder);
- ``lane_valid`` (max_lanes,) float32: 1 for the real lanes (packed first), 0 for the padding slots;
- ``seg`` (H // seg_downsample, W // seg_downsample) uint8: the binary lane mask of the auxiliary segmentation
  (every lane's polyline drawn ``seg_line_width`` x W wide; at least one cell wide).

Matching (per image, exact Hungarian by models.matching): the official maximises
``local_max(p) * p ** (1 - alpha) * (1 - L1 / n) ** alpha`` over the pairs (p the existence probability, L1 the
summed |dx| + |dy| between the 100 points sampled on the predicted and the target curve, n = 100, the second factor
clamped to [0, 1], local_max 1 where the query is the maximum of its window of k = 9 queries); the cost here is its
negative. The window: the official k = 9 (matching) and local_maximum_window_size = 9 (decoding) are set for its 40
(TuSimple, 640 px) and 50 (CULane, 800 px) queries; `scaled_window` keeps the fraction of the query row it covers
for narrower inputs (two lanes survive only (k + 1) / 2 queries apart: 9 keeps at most 4 of 20 queries' lanes). Loss:
BCE on the existence logits (positives weight 1, negatives 0.4: the official's pos_weight 1 / 0.4
divided back), L1 between the matched curves' sampled points (summed over x and y, over the matched lanes x 100 of
the whole batch), BCE of the auxiliary segmentation (weights 1 / 0.4 likewise, logits bilinearly resized to the
mask), weighted 0.1, 1 and 0.75 as the official config.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from lanevil_train.models.bezierlanenet.bezier import fit_bezier, sample_bezier, sub_curve
from lanevil_train.models.matching import match_batch

NUM_CONTROL_POINTS = 4
# The official local-maximum window and the fewest queries it is used with (pytorch-auto-drive configs/lane_detection/
# bezierlanenet/resnet18_tusimple_aug1b.py: local_maximum_window_size=9 at input 360x640, stride 16: 40 queries;
# the CULane configs: the same 9 at 800 px, 50 queries; common/optims/matchingloss_bezier.py: k=9).
OFFICIAL_WINDOW, OFFICIAL_QUERIES = 9, 40
AUTO = "auto"


# ---------------------------------------------------------------------------------------------- targets
def fit_lane(lane: np.ndarray, image_size: tuple[int, int], num_sample_points: int = 100) -> np.ndarray | None:
    """A lane (N, 2) in input pixels -> its in-image cubic Bezier (4, 2) in normalised coordinates, or None when
    fewer than two of the curve's sampled points lie inside the image."""
    h, w = image_size
    points = np.asarray(lane, dtype=np.float64)
    keep = np.concatenate([[True], np.any(np.diff(points, axis=0) != 0, axis=1)])  # drop repeated points
    points = points[keep] / np.array([w, h], dtype=np.float64)
    if len(points) < 2:
        return None
    cps = fit_bezier(points)
    ts = np.linspace(0.0, 1.0, num_sample_points)
    pts = sample_bezier(cps, ts)
    inside = np.flatnonzero((pts[:, 0] > 0) & (pts[:, 0] < 1) & (pts[:, 1] > 0) & (pts[:, 1] < 1))
    if len(inside) < 2:
        return None
    if inside[0] == 0 and inside[-1] == num_sample_points - 1:
        return cps
    return sub_curve(cps, ts[inside[0]], ts[inside[-1]])


def lane_mask(lanes: list[np.ndarray], image_size: tuple[int, int], downsample: int, line_width: float) -> np.ndarray:
    """uint8 (H // downsample, W // downsample) mask, 1 within line_width / 2 input pixels of a lane's polyline
    (at least half a cell, so a lane marks a cell on every row it crosses)."""
    h, w = image_size
    mh, mw = h // downsample, w // downsample
    cell_h, cell_w = h / mh, w / mw
    radius = max(line_width / 2.0, 0.5 * max(cell_h, cell_w))
    ys = (np.arange(mh) + 0.5) * cell_h - 0.5  # cell centres in input pixels
    xs = (np.arange(mw) + 0.5) * cell_w - 0.5
    mask = np.zeros((mh, mw), dtype=np.uint8)
    for lane in lanes:
        pts = np.asarray(lane, dtype=np.float64)
        if len(pts) < 2:
            continue
        rows = np.flatnonzero((ys >= pts[:, 1].min() - radius) & (ys <= pts[:, 1].max() + radius))
        cols = np.flatnonzero((xs >= pts[:, 0].min() - radius) & (xs <= pts[:, 0].max() + radius))
        if not len(rows) or not len(cols):
            continue
        grid = np.stack(np.meshgrid(xs[cols], ys[rows]), axis=-1).reshape(-1, 1, 2)  # (M, 1, 2)
        a, b = pts[:-1][None], pts[1:][None]  # (1, S, 2)
        ab = b - a
        t = np.clip(((grid - a) * ab).sum(-1) / np.maximum((ab**2).sum(-1), 1e-12), 0.0, 1.0)
        dist = np.linalg.norm(grid - (a + t[..., None] * ab), axis=-1).min(axis=1)
        mask[np.ix_(rows, cols)] |= (dist <= radius).reshape(len(rows), len(cols)).astype(np.uint8)
    return mask


def encode_targets(lanes: list[np.ndarray], image_size: tuple[int, int], max_lanes: int, seg_downsample: int,
                   seg_line_width: float, num_sample_points: int = 100) -> dict[str, np.ndarray]:
    """The targets of one image (see the module docstring). More lanes inside the image than max_lanes is an
    error; a lane with no in-image part is dropped."""
    curves = [c for c in (fit_lane(lane, image_size, num_sample_points) for lane in lanes) if c is not None]
    if len(curves) > max_lanes:
        raise ValueError(f"encode: {len(curves)} lanes inside the {image_size[1]}x{image_size[0]} image but "
                         f"max_lanes={max_lanes}; raise the head's max_lanes")
    control_points = np.zeros((max_lanes, NUM_CONTROL_POINTS, 2), dtype=np.float32)
    valid = np.zeros(max_lanes, dtype=np.float32)
    for i, cps in enumerate(curves):
        control_points[i], valid[i] = cps, 1.0
    seg = lane_mask(lanes, image_size, seg_downsample, seg_line_width * image_size[1])
    return {"control_points": control_points, "lane_valid": valid, "seg": seg}


# ---------------------------------------------------------------------------------------------- matching
def scaled_window(num_queries: int) -> int:
    """The local-maximum window for `num_queries` queries: 9 x Q / 40 (the official window's share of the query
    row) to the nearest odd number, at least 1 and at most the official 9 (which the official keeps at 50 queries
    too): 9 at 40 or more queries, 5 at 20 (320 px), 3 at 10."""
    share = OFFICIAL_WINDOW * num_queries / OFFICIAL_QUERIES
    nearest_odd = 2 * math.floor((share - 1) / 2 + 0.5) + 1
    return int(min(OFFICIAL_WINDOW, max(1, nearest_odd)))


def resolve_window(window, num_queries: int, key: str) -> int:
    """An int window as given (0: off; else odd), or "auto": `scaled_window(num_queries)`; a ValueError naming
    `key` otherwise."""
    if window == AUTO:
        return scaled_window(num_queries)
    if isinstance(window, bool) or not isinstance(window, (int, float)) or int(window) != window or window < 0 \
            or (window % 2 == 0 and window != 0):
        raise ValueError(f"{key} must be \"auto\" (scaled to the {num_queries} queries: {scaled_window(num_queries)}),"
                         f" 0 (off) or an odd positive integer, got {window!r}")
    return int(window)


def local_maximum(prob: torch.Tensor, window: int) -> torch.Tensor:
    """(B, Q) bool: query q is the maximum of the `window` queries centred on it, ties going to the leftmost (the
    official's max_pool1d(return_indices) == index test), so a plateau keeps one query. window 0 keeps all."""
    if window <= 0:
        return torch.ones_like(prob, dtype=torch.bool)
    r = (window - 1) // 2
    padded = F.pad(prob, (r, r), value=float("-inf"))
    windows = padded.unfold(-1, 2 * r + 1, 1)  # (B, Q, 2r + 1)
    left, right = windows[..., :r], windows[..., r + 1:]
    return (left < prob[..., None]).all(-1) & (right <= prob[..., None]).all(-1)


def sample_points(control_points: torch.Tensor, num_sample_points: int) -> torch.Tensor:
    """(..., 4, 2) control points -> (..., num_sample_points, 2) points at evenly spaced t."""
    ts = torch.linspace(0.0, 1.0, num_sample_points, device=control_points.device, dtype=control_points.dtype)
    return sample_bezier(control_points, ts)


def matching_cost(logits: torch.Tensor, curves: torch.Tensor, target_cps: torch.Tensor, alpha: float = 0.8,
                  window: int = 9, num_sample_points: int = 100) -> torch.Tensor:
    """(B, Q, L) cost of giving target l to query q (lower is better): minus the official matching score
    local_max * p ** (1 - alpha) * clamp(1 - L1 / n, 0, 1) ** alpha. logits (B, Q), curves (B, Q, 4, 2) and
    target_cps (B, L, 4, 2) normalised."""
    with torch.no_grad():
        prob = logits.float().sigmoid()
        pred = sample_points(curves.float(), num_sample_points).flatten(-2)  # (B, Q, 2n)
        tgt = sample_points(target_cps.float(), num_sample_points).flatten(-2)  # (B, L, 2n)
        l1 = (pred[:, :, None, :] - tgt[:, None, :, :]).abs().sum(-1)  # (B, Q, L)
        curve_score = (1.0 - l1 / num_sample_points).clamp(0.0, 1.0)
        lm = local_maximum(prob, window).float()
        score = lm[..., None] * prob[..., None] ** (1.0 - alpha) * curve_score**alpha
        return -score


def assign(logits: torch.Tensor, curves: torch.Tensor, target_cps: torch.Tensor, valid: torch.Tensor,
           alpha: float = 0.8, window: int = 9, num_sample_points: int = 100):
    """(batch index, query index, target index) of the matched pairs, each (M,) long, one per real target."""
    counts = valid.sum(1).round().long().tolist()
    pairs = match_batch(matching_cost(logits, curves, target_cps, alpha, window, num_sample_points), counts)
    device = logits.device
    def cat(parts) -> torch.Tensor:
        return torch.from_numpy(np.concatenate(parts) if parts else np.zeros(0, np.int64)).to(device)

    bi = [np.full(len(p), b, dtype=np.int64) for b, (p, _) in enumerate(pairs)]
    return cat(bi), cat([p for p, _ in pairs]), cat([t for _, t in pairs])


# ---------------------------------------------------------------------------------------------- loss
def weighted_bce(logits: torch.Tensor, targets: torch.Tensor, negative_weight: float) -> torch.Tensor:
    """Elementwise BCE with positives weighted 1 and negatives `negative_weight` (the official's pos_weight =
    1 / negative_weight, the loss then divided by it)."""
    pos_weight = torch.tensor(1.0 / negative_weight, device=logits.device, dtype=torch.float32)
    return F.binary_cross_entropy_with_logits(logits.float(), targets.float(), pos_weight=pos_weight,
                                              reduction="none") / pos_weight


def bezier_losses(raw: dict[str, torch.Tensor], targets: dict[str, torch.Tensor], alpha: float = 0.8,
                  window: int = 9, num_sample_points: int = 100, negative_weight: float = 0.4,
                  seg_negative_weight: float = 0.4) -> dict[str, torch.Tensor]:
    """The three unweighted loss terms of each image, (B,) each: "label", "curve", "seg" (zero without the
    training-only "seg_logits"). The curve term keeps the official's batch normalisation (the summed L1 over the
    batch's matched lanes x points), shared out so that its batch mean is the official value."""
    logits, curves = raw["logits"], raw["curves"]
    b = logits.shape[0]
    target_cps = targets["control_points"].to(curves.device).float()
    valid = targets["lane_valid"].to(curves.device).float()
    bi, qi, ti = assign(logits.detach(), curves.detach(), target_cps, valid, alpha, window, num_sample_points)
    labels = torch.zeros_like(logits, dtype=torch.float32)
    labels[bi, qi] = 1.0
    label = weighted_bce(logits, labels, negative_weight).mean(1)
    pair_l1 = (sample_points(curves[bi, qi].float(), num_sample_points)
               - sample_points(target_cps[bi, ti], num_sample_points)).abs().sum((-1, -2))  # (M,)
    curve_sum = torch.zeros(b, device=curves.device, dtype=torch.float32).index_add(0, bi, pair_l1)
    normaliser = max(len(bi) * num_sample_points, 1)
    curve = curve_sum * (b / normaliser)
    if "seg_logits" in raw:
        seg_t = targets["seg"].to(curves.device).float()
        seg_logits = F.interpolate(raw["seg_logits"].float(), size=seg_t.shape[-2:], mode="bilinear",
                                   align_corners=True)[:, 0]
        seg = weighted_bce(seg_logits, seg_t, seg_negative_weight).mean((1, 2))
    else:
        seg = torch.zeros(b, device=curves.device)
    return {"label": label, "curve": curve, "seg": seg}


__all__ = ["assign", "bezier_losses", "encode_targets", "fit_lane", "lane_mask", "local_maximum",
           "matching_cost", "resolve_window", "sample_points", "scaled_window"]
