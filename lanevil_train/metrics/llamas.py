"""LLAMAS F1: CULane's IoU F1 as the official LLAMAS evaluation computes it (a Python procedure, not CULane's C++).

The official evaluation (``utils/llamas_metric.py`` of lucastabelini/LaneATT at 2f8583b, which its README l. 144
calls the official LLAMAS metric; CLRNet's ``clrnet/utils/llamas_metric.py`` at 7269e9d is the same procedure with
several IoU thresholds, and ``clrnet/datasets/llamas.py`` l. 176-180 reports F1 at 0.5), line numbers of LaneATT's:

* Image 717 x 1276 (``LLAMAS_IMG_RES``, l. 33), lane width 30 (l. 152), IoU threshold 0.5, strict (l. 97, 112);
  LaneATT calls it with ``unofficial=False`` (``lib/datasets/llamas.py`` l. 126), CLRNet too (l. 176-179): the
  drawn ("discrete") IoU.
* Ground truth (l. 136-149): the four per-row lanes of each label (data/formats/llamas.py) with more than one row
  of x >= 0, then only rows 300..716 kept (``add_ys``, l. 36-43): the points (x, row), x >= 0, drawn as they are.
* Predictions (l. 118-129): the ``.lines.txt`` lanes with at least 2 points (shorter ones are not counted);
  each replaced by ``splprep([x, y], s=0, k=min(3, n - 1))`` sampled at 50 evenly spaced parameters
  (``interpolate_lane``, l. 87-94; the ``t=n`` argument is ignored by splprep's default task 0).
* Drawing (l. 46-68): ``lane.astype(np.int32)`` (truncation toward zero), ``cv2.line`` per consecutive pair,
  thickness 30, on a zeroed 717 x 1276 canvas; IoU = |A & B| / |A | B|.
* Matching (l. 111-115): ``scipy.optimize.linear_sum_assignment(1 - iou)``; TP = matched pairs with IoU > 0.5,
  FP = #pred - TP, FN = #gt - TP; an image without predictions gives FN = #gt, without ground truth FP = #pred
  (l. 99-102); precision, recall and F1 from the sums (l. 165-177).

So it differs from CULane's evaluator (metrics/culane.py): FITPACK's spline, 50 samples per lane (not per
segment), truncation instead of rounding, the ground truth not interpolated and cut at row 300, the exact
assignment, another image size. Where the official code would fail, this one decides: a prediction whose
consecutive points repeat has them dropped before the spline (FITPACK refuses a zero step), and an IoU of two
empty masks (0/0, which ``linear_sum_assignment`` refuses) counts as 0. The drawing reuses metrics/culane.py's
canvases (``cv2.polylines``: the same thick lines as per-pair ``cv2.line``).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from lanevil_train.metrics.culane import _Mask, lane_points, thread_canvases

LLAMAS_HEIGHT, LLAMAS_WIDTH = 717, 1276
LLAMAS_LANE_WIDTH = 30
LLAMAS_FIRST_ROW = 300  # add_ys: the ground truth is scored on rows 300..716
PRED_SAMPLES = 50


def llamas_gt_lane(lane: np.ndarray) -> np.ndarray | None:
    """The scored part of a ground-truth lane: points with x >= 0 on rows >= 300, by row; None below 2 points."""
    lane = lane_points(lane, "gt lane")
    if (lane[:, 0] >= 0).sum() <= 1:
        return None
    keep = (lane[:, 1] >= LLAMAS_FIRST_ROW) & (lane[:, 0] >= 0)
    kept = lane[keep]
    kept = kept[np.argsort(kept[:, 1], kind="stable")]
    return kept if len(kept) > 1 else None  # the official asserts > 1 here (add_ys l. 41)


def interpolate_prediction(lane: np.ndarray, samples: int = PRED_SAMPLES) -> np.ndarray:
    """interpolate_lane: FITPACK's interpolating spline through the points, sampled at ``samples`` parameters."""
    from scipy.interpolate import splev, splprep

    lane = lane_points(lane, "pred lane")
    step = np.any(np.diff(lane, axis=0) != 0, axis=1)
    lane = lane[np.concatenate([[True], step])]
    if len(lane) < 2:
        return lane
    tck, _ = splprep([lane[:, 0], lane[:, 1]], s=0, k=min(3, len(lane) - 1))
    return np.array(splev(np.linspace(0.0, 1.0, samples), tck)).T


def _polyline(points: np.ndarray) -> np.ndarray:
    """Integer polyline (astype(np.int32): truncation), consecutive repeats dropped (they add no pixel)."""
    pts = np.clip(points, np.iinfo(np.int32).min, np.iinfo(np.int32).max).astype(np.int32)
    keep = np.concatenate([[True], np.any(pts[1:] != pts[:-1], axis=1)])
    return np.ascontiguousarray(pts[keep])


def llamas_image_counts(
    pred_lanes: Sequence[object],
    gt_lanes: Sequence[object],
    lane_width: int = LLAMAS_LANE_WIDTH,
    iou_threshold: float = 0.5,
) -> tuple[int, int, int]:
    """(TP, FP, FN) of one image as the official LLAMAS evaluation counts them (lanes in 1276 x 717 pixels)."""
    from scipy.optimize import linear_sum_assignment

    preds = [p for p in (lane_points(lane, f"pred lane {k}") for k, lane in enumerate(pred_lanes)) if len(p) >= 2]
    gts = [g for g in (llamas_gt_lane(lane) for lane in gt_lanes) if g is not None]
    if not preds:
        return 0, 0, len(gts)
    if not gts:
        return 0, len(preds), 0
    canvases = thread_canvases(LLAMAS_HEIGHT, LLAMAS_WIDTH)
    drawn: list[_Mask] = []
    try:
        for lane in [interpolate_prediction(p) for p in preds] + gts:
            drawn.append(canvases.draw(len(drawn), _polyline(lane), lane_width))
        pm, gm = drawn[: len(preds)], drawn[len(preds):]
        ious = np.array([[canvases.iou(p, g) for g in gm] for p in pm])
    finally:
        canvases.clear(drawn)
    ious = np.nan_to_num(ious, nan=0.0)
    rows, cols = linear_sum_assignment(1 - ious)
    tp = int((ious[rows, cols] > iou_threshold).sum())
    return tp, len(preds) - tp, len(gts) - tp
