"""CurveLanes F1: the CULane IoU F1 at CurveLanes' evaluation size and lane width, as its evaluation code defines it.

The dataset kit (SoulmateB/CurveLanes at c47eca7, README.md l. 127-129) ships no evaluation tool ("To be
provided"). The CurveLanes authors' code is ``LaneMetricCore`` of huawei-noah/vega (``vega/metrics/pytorch/
lane_metric.py`` at 12e37a1, the CurveLane-NAS authors' AutoML toolkit), which aliyun/conditional-lane-detection
copies (``tools/condlanenet/lane_metric.py`` at 6deb6c2) and CLRerNet's CurveLanes branch imports (hirotomusiker/
CLRerNet ``libs/datasets/curvelanes_dataset.py`` at 33add07, ``CurvelanesDataset.evaluate``). Its procedure (line
numbers of vega's file):

* Settings: a 224 x 224 evaluation canvas, 5 px lanes, IoU threshold 0.5 (conditional-lane-detection
  ``tools/condlanenet/curvelanes/test_curvelanes.py`` l. 40-42 and its ``LaneMetricCore(..., iou_thresh=0.5)``;
  CLRerNet ``CurvelanesDataset.evaluate(eval_width=224, eval_height=224, iou_thresh=0.5, lane_width=5)``). vega's
  own CULane example uses 1640 x 590 and 30 px (``examples/nas/auto_lane/auto_lane.yml`` l. 79-82): the numbers
  are the caller's, and CurveLanes results are reported with 224, 224, 5, 0.5.
* Scaling (``resize_lane``, l. 160-172; ``evaluate_core``, l. 236-241): every point of a lane, ground truth and
  prediction alike, becomes (x / (W / 224), y / (H / 224)) with (W, H) the original image's size (2560 x 1440,
  1570 x 660, 1280 x 720: the aspect ratio is not kept).
* Interpolation (``spline_interp``, l. 54-76; ``calc_params``, l. 79-157): on the scaled points, a natural cubic
  spline (second derivative 0 at both ends, solved by the Thomas algorithm) in x(t), y(t), t the chord length of
  each segment, sampled at t = 0, 1, 2, ... < h on every segment (one sample per evaluation pixel of chord), then
  the last point; a 2-point lane is its segment sampled the same way. (CULane's tool takes 50 samples per
  segment and rounds: metrics/culane.py.)
* Drawing (``calc_iou``, l. 175-205): each sample ``int()`` (truncated toward zero), ``cv2.line`` between
  consecutive samples, thickness 5, on a zeroed 224 x 224 canvas; IoU = |A & B| / |A | B|, 0 when both are empty.
* Matching (l. 243-257): ``scipy.optimize.linear_sum_assignment(1 - iou)`` over all ground-truth x predicted
  lanes; a matched pair is a hit when IoU > 0.5 (strict). Lanes with no point are dropped first (l. 296-308),
  so a 1-point lane counts but never hits. Per image: ground-truth, predicted and hit counts; summed:
  precision = hits / predictions, recall = hits / ground truth, F1 their harmonic mean (``summary``, l. 318-326);
  here TP = hits, FP = predictions - TP, FN = ground truth - TP (``culane_summary``).
* Predictions (CLRerNet ``convert_coords_laneatt``): each lane read at the rows 0, 8, 16, ... < H of the original
  image, x kept within [0, W), bottom point first.

Where the kit would fail, this one decides: consecutive repeated points of a lane are dropped before the spline
(a zero chord divides 0 by 0 there and ``int(nan)`` raises), and coordinates are clipped to int32 before drawing.
The drawing reuses metrics/culane.py's canvases (``cv2.polylines``: the same thick lines as per-pair
``cv2.line``; a lane whose samples all fall in one pixel is drawn as that pixel's dot, as ``cv2.line(p, p)`` does).

``python -m lanevil_train.metrics curvelanes --pred-dir P --root R`` scores a tree of ``.lines.txt`` predictions
(``<P>/<split>/images/<name>.lines.txt``, what ``task=evaluate task.predictions=true`` writes in
``predictions/culane/``) against the official labels, drawn in the labels' point order; ``task=evaluate
data=curvelanes`` scores each image in process (evaluation/lane_records.py) from the dataset's lanes, which the
package keeps bottom point first (the labels' order wherever a lane's y decreases along it).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from lanevil_train.metrics.culane import culane_summary, lane_points, thread_canvases

__all__ = ["CURVELANES_EVAL_WIDTH", "CURVELANES_EVAL_HEIGHT", "CURVELANES_LANE_WIDTH", "CURVELANES_IOU",
           "PRED_ROW_STEP", "kit_samples", "kit_polyline", "curvelanes_image_counts", "evaluate_curvelanes_dirs"]

CURVELANES_EVAL_WIDTH = CURVELANES_EVAL_HEIGHT = 224
CURVELANES_LANE_WIDTH = 5
CURVELANES_IOU = 0.5
PRED_ROW_STEP = 8  # CLRerNet's prediction rows: numpy.arange(0, H, 8)
_INT32 = np.iinfo(np.int32)


def _natural_spline_coefficients(p: np.ndarray, h: np.ndarray, slopes: np.ndarray) -> tuple[np.ndarray, ...]:
    """(b, c, d) per segment of one coordinate of the natural cubic spline through p (>= 3 points): value
    a + b t + c t^2 + d t^3 with a = p[i], t in [0, h[i]]; the Thomas algorithm in the kit's operation order."""
    n, m = len(p), len(p) - 2
    hl, sl = h.tolist(), slopes.tolist()
    sub, diag, sup = hl[:m], [2 * (hl[i] + hl[i + 1]) for i in range(m)], hl[1:m + 1]
    rhs = [6 * (sl[i + 1] - sl[i]) for i in range(m)]
    sup[0], rhs[0] = sup[0] / diag[0], rhs[0] / diag[0]
    for i in range(1, m):
        base = diag[i] - sub[i] * sup[i - 1]
        sup[i] = sup[i] / base
        rhs[i] = (rhs[i] - sub[i] * rhs[i - 1]) / base
    second = [0.0] * n  # the second derivative at each point, 0 at both ends
    second[n - 2] = rhs[m - 1]
    for i in range(m - 2, -1, -1):
        second[i + 1] = rhs[i] - sup[i] * second[i + 2]
    s = np.array(second)
    b = slopes - (2 * h * s[:-1] + h * s[1:]) / 6
    return b, s[:-1] / 2, (s[1:] - s[:-1]) / (6 * h)


def kit_samples(points: object) -> np.ndarray:
    """The kit's ``spline_interp(step_t=1)`` of a lane (points in evaluation pixels): (M, 2) float64 samples at
    t = 0, 1, ... < h of every chord, then the last point; consecutive repeats dropped first; a lane left with
    fewer than 2 points is returned as it is."""
    p = lane_points(points, "lane")
    if len(p) > 1:
        p = p[np.concatenate([[True], np.any(p[1:] != p[:-1], axis=1)])]
    if len(p) < 2:
        return p.copy()
    dx, dy = p[1:, 0] - p[:-1, 0], p[1:, 1] - p[:-1, 1]
    h = np.sqrt(dx * dx + dy * dy)
    sx, sy = dx / h, dy / h
    if len(p) == 2:
        zero = np.zeros(1)
        (bx, cx, ex), (by, cy, ey) = (sx, zero, zero), (sy, zero, zero)
    else:
        (bx, cx, ex), (by, cy, ey) = (_natural_spline_coefficients(p[:, 0], h, sx),
                                      _natural_spline_coefficients(p[:, 1], h, sy))
    counts = np.ceil(h).astype(np.int64)  # t = 0, 1, ... while t < h
    seg = np.repeat(np.arange(len(h)), counts)
    t = (np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)).astype(np.float64)
    out = np.empty((len(t) + 1, 2))
    for axis, (b, c, e) in enumerate(((bx, cx, ex), (by, cy, ey))):
        a = p[:-1, axis][seg]
        out[:-1, axis] = a + b[seg] * t + c[seg] * t * t + e[seg] * t * t * t
    out[-1] = p[-1]
    return out


def kit_polyline(samples: np.ndarray) -> np.ndarray | None:
    """Integer drawing polyline of spline samples (``int()``: truncation toward zero), consecutive repeats dropped
    (they add no pixel), at least 2 points (a lane in one pixel is its dot); None when nothing is drawn (< 2
    samples)."""
    if len(samples) < 2:
        return None
    pts = np.trunc(np.clip(samples, _INT32.min, _INT32.max)).astype(np.int32)
    keep = np.concatenate([[True], np.any(pts[1:] != pts[:-1], axis=1)])
    pts = pts[keep]
    if len(pts) == 1:
        pts = np.concatenate([pts, pts])
    return np.ascontiguousarray(pts)


def curvelanes_image_counts(
    pred_lanes: Sequence[object],
    gt_lanes: Sequence[object],
    image_size: tuple[int, int],
    eval_width: int = CURVELANES_EVAL_WIDTH,
    eval_height: int = CURVELANES_EVAL_HEIGHT,
    lane_width: int = CURVELANES_LANE_WIDTH,
    iou_threshold: float = CURVELANES_IOU,
) -> tuple[int, int, int]:
    """(TP, FP, FN) of one image as the CurveLanes evaluation counts them: lanes in the original image's pixels,
    ``image_size`` its (height, width), drawn at ``eval_width`` x ``eval_height``."""
    from scipy.optimize import linear_sum_assignment

    height, width = image_size
    if min(height, width, eval_width, eval_height, lane_width) < 1:
        raise ValueError(f"image size {width}x{height}, evaluation size {eval_width}x{eval_height} and lane width "
                         f"{lane_width} must be positive")
    preds = [p for p in (lane_points(lane, f"pred lane {k}") for k, lane in enumerate(pred_lanes)) if len(p)]
    gts = [g for g in (lane_points(lane, f"gt lane {k}") for k, lane in enumerate(gt_lanes)) if len(g)]
    if not preds or not gts:
        return 0, len(preds), len(gts)
    scale = np.array([width / eval_width, height / eval_height])  # the kit's divisors (x_ratio, y_ratio)
    canvases = thread_canvases(eval_height, eval_width)
    drawn = []
    try:
        masks = []
        for lane in gts + preds:
            poly = kit_polyline(kit_samples(lane / scale))
            if poly is None:
                masks.append(None)
                continue
            drawn.append(canvases.draw(len(drawn), poly, lane_width))
            masks.append(drawn[-1])
        gm, pm = masks[: len(gts)], masks[len(gts):]
        ious = np.array([[0.0 if g is None or p is None else canvases.iou(g, p) for p in pm] for g in gm])
    finally:
        canvases.clear(drawn)
    ious = np.nan_to_num(ious, nan=0.0)  # both masks empty: the kit's 0
    rows, cols = linear_sum_assignment(1 - ious)
    tp = int((ious[rows, cols] > iou_threshold).sum())
    return tp, len(preds) - tp, len(gts) - tp


def evaluate_curvelanes_dirs(
    pred_dir: str | Path,
    root: str | Path,
    split: str = "valid",
    list_file: str | Path | None = None,
    image_size: tuple[int, int] | None = None,
    eval_width: int = CURVELANES_EVAL_WIDTH,
    eval_height: int = CURVELANES_EVAL_HEIGHT,
    lane_width: int = CURVELANES_LANE_WIDTH,
    iou_threshold: float = CURVELANES_IOU,
) -> dict:
    """Score ``<pred_dir>/<split>/images/<name>.lines.txt`` (a missing file: no lanes) against the labels of a
    CurveLanes split (``<root>/<split>/<split>.txt`` or ``list_file``); every label is read, and every image size
    found (``image_size`` (H, W) for all, else each image's header), before any counting."""
    from lanevil_train.data.formats import curvelanes as layout
    from lanevil_train.metrics.culane_files import read_lines_file

    pred_dir, root = Path(pred_dir), Path(root)
    if split not in ("train", "valid"):
        raise ValueError(f"split {split!r}: expected train or valid (the test split's labels are not public)")
    if not pred_dir.is_dir():
        raise FileNotFoundError(f"--pred-dir {pred_dir} is not a directory (expected <dir>/{split}/images/"
                                f"<name>.lines.txt, e.g. an evaluation's predictions/culane)")
    list_path = layout.official_list_file(root, split) if list_file is None else Path(root, list_file)
    entries = layout.read_list_file(list_path)
    if not entries:
        raise ValueError(f"{list_path} lists no images")
    split_dir = root / split
    gts = [layout.read_curvelanes_label(layout.label_path_for(split_dir, entry)) for _, entry in entries]
    sizes = [image_size or layout.image_size_of(split_dir / entry, "--image-size WxH") for _, entry in entries]
    pred_paths = [(pred_dir / split / entry).with_suffix(".lines.txt") for _, entry in entries]
    if not any(p.is_file() for p in pred_paths):
        raise FileNotFoundError(f"no prediction file under {pred_dir} for the {len(entries)} images of {list_path} "
                                f"(the first expected: {pred_paths[0]})")
    tp = fp = fn = 0
    for path, gt, size in zip(pred_paths, gts, sizes):
        preds = read_lines_file(str(path), side="prediction")
        a, b, c = curvelanes_image_counts(preds, gt, size, eval_width, eval_height, lane_width, iou_threshold)
        tp, fp, fn = tp + a, fp + b, fn + c
    return {**culane_summary(tp, fp, fn), "images": len(entries), "eval_width": eval_width,
            "eval_height": eval_height, "lane_width": lane_width, "iou_threshold": iou_threshold}
