"""TuSimple lane accuracy / FP / FN / F1, reproducing the official evaluation arithmetic.

Reference: TuSimple/tusimple-benchmark ``evaluate/lane.py`` (class ``LaneEval``, methods
``get_angle``, ``line_accuracy``, ``bench``, ``bench_one_submit``). Per image, for each GT lane:
fit x = k*y + b by least squares over its valid points (x >= 0), theta = arctan(k) (0 with
fewer than 2 points), threshold = pixel_thresh / cos(theta); a pred lane's accuracy against it
is the share of ALL h_samples where |pred - gt| < threshold, invalid points of both being
mapped to -100 first (so two invalid points agree). The GT lane's accuracy is the max over preds;
it is matched when that is >= pt_thresh. Then fp = #pred - #matched, one FN is forgiven and the
worst lane accuracy dropped when there are more than 4 GT lanes, and accuracy / fp / fn are
normalised by max(min(4, #gt), 1), #pred and max(min(#gt, 4), 1). An image with more than
#gt + 2 preds scores (0, 0, 1); a pred lane whose length differs from h_samples is a
"Format of lanes error". The official run-time penalty (run_time > 200 ms scores (0, 0, 1))
is deliberately NOT applied: run time is measured elsewhere and is not comparable across
machines. The official fit uses sklearn's LinearRegression; here the same least-squares slope
is computed in closed form with numpy (equal up to float rounding). The file-level sum runs in the
prediction file's order, as the official loop does, so equal per-image values give bit-equal means.

F1_count (not official; beside the papers' F1): the papers' TuSimple F1 (CLRNet's, from the mean FP and FN
rates with tp = 1 - FP) gives 2/3 to a model that predicts nothing (FP 0, FN 1 -> P 1, R 1/2). F1_count counts
lanes instead. Per image, a predicted and a GT lane match under the official criterion (line accuracy >=
pt_thresh, ``evaluate/lane.py`` lines 40-45); TP is the largest number of disjoint (pred, GT) matched pairs,
FP = #pred - TP, FN = #gt - TP. Summed over images, F1_count = 2 TP / (2 TP + FP + FN) (= 2PR / (P + R)), 0 when
TP = 0. TP equals the official ``matched`` unless one prediction is the match of several GT lanes (there the
official fp goes negative; here the extra GT lanes are misses). Every lane counts: neither the "more than 4 GT
lanes" forgiveness nor the "more than #gt + 2 predictions" penalty applies to the counts.

This module needs numpy only (the ``tusimple`` command imports nothing else); the torchmetrics wrapper
is ``wrappers.TuSimpleMetric``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from lanevil_train.lanes import lanes_to_rows
from lanevil_train.rules import is_number

__all__ = [
    "tusimple_count_f1",
    "tusimple_image_scores",
    "tusimple_lane_scores",
    "tusimple_summary",
    "evaluate_tusimple_files",
]

_INVALID_FILL = -100.0  # the official line_accuracy maps every x < 0 to -100


def _lane_angles(gt: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Per GT row, arctan of the least-squares slope dx/dy over its valid points (0 if < 2)."""
    valid = gt >= 0
    n = valid.sum(axis=1)
    safe_n = np.maximum(n, 1)
    y = np.broadcast_to(ys, gt.shape)
    ybar = np.where(valid, y, 0.0).sum(axis=1) / safe_n
    xbar = np.where(valid, gt, 0.0).sum(axis=1) / safe_n
    dy = np.where(valid, y - ybar[:, None], 0.0)
    dx = np.where(valid, gt - xbar[:, None], 0.0)
    sxy = (dy * dx).sum(axis=1)
    syy = (dy * dy).sum(axis=1)
    ok = (n > 1) & (syy > 0)  # syy == 0 only for repeated rows: lstsq's min-norm slope is 0 too
    k = np.where(ok, sxy / np.where(ok, syy, 1.0), 0.0)
    return np.where(n > 1, np.arctan(k), 0.0)


def _first_non_finite(values: np.ndarray) -> tuple[int, ...] | None:
    """Index of the first NaN / inf in ``values`` (row-major), or None when all are finite."""
    finite = np.isfinite(values)
    if finite.all():
        return None
    return tuple(int(i) for i in np.argwhere(~finite)[0])


def _checked_rows(pred_rows, gt_rows, h_samples) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pred (P, H), gt (G, H), ys (H,)) as float64 arrays; ValueError naming the bad input otherwise."""
    ys = np.asarray(h_samples, dtype=np.float64).reshape(-1)
    h = len(ys)
    pred = np.asarray(pred_rows, dtype=np.float64)
    gt = np.asarray(gt_rows, dtype=np.float64)
    if pred.size == 0 and pred.ndim < 2:  # [] means "no lanes"
        pred = pred.reshape(0, h)
    if gt.size == 0 and gt.ndim < 2:
        gt = gt.reshape(0, h)
    if pred.ndim != 2 or pred.shape[1] != h:
        raise ValueError(
            f"Format of lanes error: pred_rows must be (P, {h}) (one x per h_sample), got {pred.shape}"
        )
    if gt.ndim != 2 or gt.shape[1] != h:
        raise ValueError(f"gt_rows must be (G, {h}) (one x per h_sample), got shape {gt.shape}")
    for name, rows in (("pred_rows", pred), ("gt_rows", gt)):
        bad = _first_non_finite(rows)
        if bad is not None:
            j, k = bad
            raise ValueError(f"{name}: lane {j} has a non-finite x ({rows[j, k]}) at h_sample index {k}; "
                             f"expected a finite x in pixels, or -2 (any x < 0) for 'no point'")
    bad = _first_non_finite(ys)
    if bad is not None:
        raise ValueError(f"h_samples: non-finite y ({ys[bad[0]]}) at index {bad[0]}; expected finite image rows "
                         f"in pixels")
    return pred, gt, ys


def _line_accuracies(pred: np.ndarray, gt: np.ndarray, ys: np.ndarray, pixel_thresh: float) -> np.ndarray:
    """(G, P) official line_accuracy of every pred lane against every GT lane (empty when either side is)."""
    n_pred, n_gt, h = pred.shape[0], gt.shape[0], len(ys)
    if n_gt == 0 or n_pred == 0:
        return np.zeros((n_gt, n_pred))
    if h == 0:
        raise ValueError("h_samples is empty but the image has GT and predicted lanes")
    thresh = pixel_thresh / np.cos(_lane_angles(gt, ys))  # (G,)
    p = np.where(pred >= 0, pred, _INVALID_FILL)
    g = np.where(gt >= 0, gt, _INVALID_FILL)
    close = np.abs(p[None, :, :] - g[:, None, :]) < thresh[:, None, None]  # (G, P, H)
    return close.sum(axis=2) / h


def _max_pairs(match: np.ndarray) -> int:
    """Largest number of disjoint (GT, pred) pairs with match[g, p] True (augmenting paths; a few lanes)."""
    owner = [-1] * match.shape[1]  # owner[p]: the GT lane pred p is paired with

    def augment(g: int, seen: set[int]) -> bool:
        for p in np.flatnonzero(match[g]).tolist():
            if p not in seen:
                seen.add(p)
                if owner[p] < 0 or augment(owner[p], seen):
                    owner[p] = g
                    return True
        return False

    return sum(augment(g, set()) for g in range(match.shape[0]))


def _official_scores(line_accs: np.ndarray, n_pred: int, pt_thresh: float) -> tuple[float, float, float]:
    """LaneEval.bench's (accuracy, fp, fn) from the (G, P) line accuracies of an image not penalised."""
    n_gt = line_accs.shape[0]
    max_acc = line_accs.max(axis=1) if n_pred > 0 else np.zeros(n_gt)  # (G,)
    fn = float(np.count_nonzero(max_acc < pt_thresh))
    matched = n_gt - fn
    fp = n_pred - matched  # may go negative when several GT lanes match one pred (as official)
    if n_gt > 4 and fn > 0:
        fn -= 1
    s = 0.0
    for a in max_acc.tolist():  # sequential sum, as the official sum() over a list
        s += a
    if n_gt > 4:
        s -= float(max_acc.min())
    acc = s / max(min(4.0, n_gt), 1.0)
    fp_rate = fp / n_pred if n_pred > 0 else 0.0
    fn_rate = fn / max(min(n_gt, 4.0), 1.0)
    return float(acc), float(fp_rate), float(fn_rate)


def tusimple_image_scores(
    pred_rows: np.ndarray,
    gt_rows: np.ndarray,
    h_samples: np.ndarray,
    pixel_thresh: float = 20,
    pt_thresh: float = 0.85,
    with_counts: bool = False,
) -> tuple:
    """(accuracy, fp, fn) of one image as LaneEval.bench computes them (without the run-time rule); with
    ``with_counts`` also the lane counts (tp, fp_count, fn_count) of F1_count (module docstring), as ints.

    Rows are TuSimple rows: one x per h_sample, any x < 0 (TuSimple writes -2) meaning "no point".
    """
    pred, gt, ys = _checked_rows(pred_rows, gt_rows, h_samples)
    n_pred, n_gt = pred.shape[0], gt.shape[0]
    penalised = n_gt + 2 < n_pred  # official: scored (0, 0, 1) without matching
    if penalised and not with_counts:
        return 0.0, 0.0, 1.0
    line_accs = _line_accuracies(pred, gt, ys, pixel_thresh)
    scores = (0.0, 0.0, 1.0) if penalised else _official_scores(line_accs, n_pred, pt_thresh)
    if not with_counts:
        return scores
    tp = _max_pairs(line_accs >= pt_thresh)
    return scores + (tp, n_pred - tp, n_gt - tp)


def tusimple_count_f1(tp: int, fp: int, fn: int) -> float:
    """F1_count in [0, 1] from lane counts summed over images: 2 TP / (2 TP + FP + FN); 0 when TP = 0."""
    return 2.0 * tp / (2.0 * tp + fp + fn) if tp > 0 else 0.0


def tusimple_summary(acc_sum: float, fp_sum: float, fn_sum: float, num_images: int,
                     counts: tuple[int, int, int] | None = None) -> dict:
    """Dataset scores: means of the per-image values plus F1 as CLRNet/LaneATT compute it; with ``counts`` (TP,
    FP, FN lanes summed over the images) also F1_count and the counts (TP_count, FP_count, FN_count).

    F1 follows Turoad/CLRNet ``clrnet/utils/tusimple_metric.py`` lines 102-107 (the convention papers report):
    FP, FN = mean per-image rates; tp = 1 - FP; precision = tp / (tp + FP); recall = tp / (tp + FN);
    F1 = 2PR / (P + R). Where that script would divide by zero (FP = 1 and FN = 0, or P + R = 0)
    F1 is 0 here. A model that predicts nothing gets F1 2/3 (FP 0, FN 1); its F1_count is 0.
    """
    if num_images <= 0:
        raise ValueError(f"num_images must be > 0 to summarise TuSimple scores, got {num_images}")
    acc = acc_sum / num_images
    fp = fp_sum / num_images
    fn = fn_sum / num_images
    tp = 1 - fp
    precision = tp / (tp + fp)  # tp + fp == 1
    recall = tp / (tp + fn) if (tp + fn) != 0 else 0.0
    f1 = 2 * precision * recall / (precision + recall) if (precision + recall) != 0 else 0.0
    out = {"Accuracy": float(acc), "FP": float(fp), "FN": float(fn), "F1": float(f1)}
    if counts is not None:
        tp_c, fp_c, fn_c = (int(c) for c in counts)
        out.update(F1_count=tusimple_count_f1(tp_c, fp_c, fn_c), TP_count=tp_c, FP_count=fp_c, FN_count=fn_c)
    return out


def tusimple_lane_scores(pred_lanes: Sequence[np.ndarray], gt_lanes: Sequence[np.ndarray], h_samples: np.ndarray,
                         pixel_thresh: float = 20.0, pt_thresh: float = 0.85, with_counts: bool = False,
                         row_sampling: str = "linear", height: float | None = None) -> tuple:
    """(accuracy, fp, fn) of one image from lanes in pixels, sampled at its h_samples rows (the predicted lanes as
    `row_sampling` reads them, lanes.ROW_SAMPLINGS; `height` the image's, for "spline"); with ``with_counts`` also
    (tp, fp_count, fn_count) lanes, as tusimple_image_scores."""
    ys = np.asarray(h_samples, dtype=np.float64).reshape(-1)
    pred_rows = lanes_to_rows(list(pred_lanes), ys, row_sampling, height)
    return tusimple_image_scores(pred_rows, lanes_to_rows(list(gt_lanes), ys), ys, pixel_thresh, pt_thresh,
                                 with_counts)


def _read_json_lines(path: Path, required: tuple[str, ...]) -> list[tuple[int, dict]]:
    """(line number, object) for each non-blank line of a JSON-lines file; clear errors."""
    out = []
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise FileNotFoundError(f"cannot read TuSimple file {path}: {e}") from e
    for lineno, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        try:
            obj = json.loads(line)
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}:{lineno}: malformed JSON ({e.msg} at column {e.colno})") from e
        if not isinstance(obj, dict):
            raise ValueError(f"{path}:{lineno}: expected a JSON object, got {type(obj).__name__}")
        missing = [k for k in required if k not in obj]
        if missing:
            raise ValueError(f"{path}:{lineno}: missing key(s) {missing}; expected {list(required)}")
        if not isinstance(obj["raw_file"], str) or not obj["raw_file"]:
            raise ValueError(f"{path}:{lineno}: raw_file must be a non-empty string (the image's path), "
                             f"got {obj['raw_file']!r}")
        out.append((lineno, obj))
    return out


def _is_number_list(value: object) -> bool:
    """A JSON list of numbers only (no strings such as "300", no true/false, which numpy would turn into numbers)."""
    return isinstance(value, list) and all(type(v) in (int, float) for v in value)


def _h_samples(value: object, path: Path, lineno: int, raw: str) -> np.ndarray:
    """A GT line's h_samples as a 1-D float64 array; raises naming file, line and raw_file unless finite numbers."""
    where = f"{path}:{lineno}: ground truth h_samples of raw_file {raw!r}"
    if not _is_number_list(value):
        raise ValueError(f"{where} must be a list of numbers, got {str(value)[:80]}")
    ys = np.asarray(value, dtype=np.float64).reshape(-1)
    bad = _first_non_finite(ys)
    if bad is not None:
        raise ValueError(f"{where} has a non-finite y ({ys[bad[0]]}) at index {bad[0]}; expected finite image "
                         f"rows in pixels")
    return ys


def _lane_rows(value: object, ys: np.ndarray, path: Path, lineno: int, raw: str, pred: bool) -> np.ndarray:
    """A JSON line's lanes as an (L, len(ys)) float64 array; a bad lane raises naming file, line, side and lane."""
    n_rows = ys.size
    side = "prediction" if pred else "ground truth"
    rows = None  # ragged or not numbers: the loop below finds the lane
    if isinstance(value, list) and all(_is_number_list(lane) for lane in value):
        try:
            rows = np.asarray(value, dtype=np.float64)  # one conversion for the usual, well-formed line
        except ValueError:
            pass
    if rows is not None and rows.size == 0 and rows.ndim == 1:
        return np.zeros((0, n_rows))
    if rows is None or rows.ndim != 2 or rows.shape[1] != n_rows:
        for j, lane in enumerate(value if isinstance(value, list) else [value]):
            if not _is_number_list(lane):
                raise ValueError(f"{path}:{lineno}: {side} lane {j} of raw_file {raw!r} must be a list of numbers, "
                                 f"got {str(lane)[:80]}")
            arr = np.asarray(lane, dtype=np.float64)
            if arr.shape != (n_rows,):
                prefix = "Format of lanes error: " if pred else ""
                raise ValueError(f"{path}:{lineno}: {prefix}{side} lane {j} of raw_file {raw!r} has {arr.size} x "
                                 f"values but h_samples has {n_rows}")
        raise ValueError(f"{path}:{lineno}: {side} lanes of raw_file {raw!r} must be a list of lists of numbers")
    bad = _first_non_finite(rows)
    if bad is not None:
        j, k = bad
        raise ValueError(f"{path}:{lineno}: {side} lane {j} of raw_file {raw!r} has a non-finite x ({rows[j, k]}) "
                         f"at h_sample index {k} (y = {ys[k]:g}); expected a finite x in pixels, or -2 for "
                         f"'no point'")
    return rows


def _check_thresholds(pixel_thresh, pt_thresh) -> None:
    """ValueError naming the threshold unless pixel_thresh is finite > 0 and pt_thresh in (0, 1]."""
    if not is_number(pixel_thresh) or not (math.isfinite(pixel_thresh) and pixel_thresh > 0):
        raise ValueError(f"pixel_thresh (--pixel-thresh) must be a finite number of pixels > 0 (official: 20), "
                         f"got {pixel_thresh}")
    if not is_number(pt_thresh) or not 0 < pt_thresh <= 1:
        raise ValueError(f"pt_thresh (--pt-thresh) must be a fraction of matched points in (0, 1] (official: 0.85), "
                         f"got {pt_thresh}")


def evaluate_tusimple_files(
    pred_path: str | Path, gt_path: str | Path, pixel_thresh: float = 20, pt_thresh: float = 0.85
) -> dict:
    """Official file-level evaluation (bench_one_submit): JSON-lines preds vs GT, keyed by raw_file.

    Every GT image needs exactly one prediction and every prediction a GT image (as officially).
    ``run_time`` is accepted but ignored (no run-time penalty). Returns {"Accuracy", "FP", "FN", "F1"} and the
    lane counts' {"F1_count", "TP_count", "FP_count", "FN_count"} (tusimple_summary).
    """
    _check_thresholds(pixel_thresh, pt_thresh)
    pred_path, gt_path = Path(pred_path), Path(gt_path)
    gts: dict[str, tuple[int, dict]] = {}
    for lineno, obj in _read_json_lines(gt_path, ("lanes", "h_samples", "raw_file")):
        if obj["raw_file"] in gts:
            raise ValueError(
                f"{gt_path}:{lineno}: duplicate raw_file {obj['raw_file']!r} "
                f"(first at line {gts[obj['raw_file']][0]})"
            )
        gts[obj["raw_file"]] = (lineno, obj)
    preds: dict[str, tuple[int, dict]] = {}
    for lineno, obj in _read_json_lines(pred_path, ("lanes", "raw_file")):
        raw = obj["raw_file"]
        if raw in preds:
            raise ValueError(f"{pred_path}:{lineno}: duplicate prediction for raw_file {raw!r}")
        if raw not in gts:
            raise ValueError(f"{pred_path}:{lineno}: raw_file {raw!r} is not in the GT file {gt_path}")
        preds[raw] = (lineno, obj)
    if not gts:
        raise ValueError(f"GT file {gt_path} has no images")
    for raw, (gt_line, _) in gts.items():
        if raw not in preds:
            raise ValueError(f"no prediction in {pred_path} for GT image raw_file {raw!r} ({gt_path}:{gt_line})")
    acc = fp = fn = 0.0
    counts = [0, 0, 0]
    for raw, (pred_line, pred) in preds.items():  # prediction-file order: the official sums in this order
        gt_line, gt = gts[raw]
        ys = _h_samples(gt["h_samples"], gt_path, gt_line, raw)
        gt_rows = _lane_rows(gt["lanes"], ys, gt_path, gt_line, raw, pred=False)
        pred_rows = _lane_rows(pred["lanes"], ys, pred_path, pred_line, raw, pred=True)
        a, p, n, *lanes = tusimple_image_scores(pred_rows, gt_rows, ys, pixel_thresh, pt_thresh, with_counts=True)
        acc += a
        fp += p
        fn += n
        counts = [c + k for c, k in zip(counts, lanes)]
    return tusimple_summary(acc, fp, fn, len(gts), counts=tuple(counts))

