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
is computed in closed form with numpy (equal up to float rounding).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torchmetrics import Metric

from lanevil_train.lanes import lanes_to_rows

__all__ = [
    "tusimple_image_scores",
    "tusimple_lane_scores",
    "tusimple_summary",
    "TuSimpleMetric",
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


def tusimple_image_scores(
    pred_rows: np.ndarray,
    gt_rows: np.ndarray,
    h_samples: np.ndarray,
    pixel_thresh: float = 20,
    pt_thresh: float = 0.85,
) -> tuple[float, float, float]:
    """(accuracy, fp, fn) of one image as LaneEval.bench computes them (without the run-time rule).

    Rows are TuSimple rows: one x per h_sample, any x < 0 (TuSimple writes -2) meaning "no point".
    """
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
    if not (np.all(np.isfinite(pred)) and np.all(np.isfinite(gt))):
        raise ValueError("pred_rows / gt_rows contain non-finite values (use -2 for 'no point')")
    n_pred, n_gt = pred.shape[0], gt.shape[0]
    if n_gt + 2 < n_pred:
        return 0.0, 0.0, 1.0
    if n_gt > 0 and n_pred > 0:
        if h == 0:
            raise ValueError("h_samples is empty but the image has GT and predicted lanes")
        thresh = pixel_thresh / np.cos(_lane_angles(gt, ys))  # (G,)
        p = np.where(pred >= 0, pred, _INVALID_FILL)
        g = np.where(gt >= 0, gt, _INVALID_FILL)
        close = np.abs(p[None, :, :] - g[:, None, :]) < thresh[:, None, None]  # (G, P, H)
        line_accs = close.sum(axis=2) / h  # (G, P)
        max_acc = line_accs.max(axis=1)  # (G,)
    else:
        max_acc = np.zeros(n_gt)
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


def tusimple_summary(acc_sum: float, fp_sum: float, fn_sum: float, num_images: int) -> dict:
    """Dataset scores: means of the per-image values plus F1 as CLRNet/LaneATT compute it.

    F1 follows Turoad/CLRNet ``clrnet/utils/tusimple_metric.py`` (the convention papers report):
    FP, FN = mean per-image rates; tp = 1 - FP; precision = tp / (tp + FP); recall = tp / (tp + FN);
    F1 = 2PR / (P + R). Where that script would divide by zero (FP = 1 and FN = 0, or P + R = 0)
    F1 is 0 here.
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
    return {"Accuracy": float(acc), "FP": float(fp), "FN": float(fn), "F1": float(f1)}


def _as_np_lane(lane) -> np.ndarray:
    if isinstance(lane, torch.Tensor):
        lane = lane.detach().cpu().numpy()
    arr = np.asarray(lane, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"a lane must be an (N, 2) array of (x, y) pixels, got shape {arr.shape}")
    return arr


def tusimple_lane_scores(pred_lanes: Sequence[np.ndarray], gt_lanes: Sequence[np.ndarray], h_samples: np.ndarray,
                         pixel_thresh: float = 20.0, pt_thresh: float = 0.85) -> tuple[float, float, float]:
    """(accuracy, fp, fn) of one image from lanes in pixels, sampled at its h_samples rows."""
    ys = np.asarray(h_samples, dtype=np.float64).reshape(-1)
    return tusimple_image_scores(lanes_to_rows(list(pred_lanes), ys), lanes_to_rows(list(gt_lanes), ys), ys,
                                 pixel_thresh, pt_thresh)


class TuSimpleMetric(Metric):
    """TuSimple Accuracy / FP / FN / F1 over decoded lanes (pixels); DDP-safe sum states.

    Each image's lanes are sampled at its h_samples with ``lanes_to_rows`` (linear
    interpolation, -2 outside a lane's span); pass the GT file's h_samples to get the official
    score. With ``h_samples=None`` the rows are the sorted unique y values of that image's GT
    points. TuSimple GT points already lie on its h_samples, so every GT point is kept exactly,
    but rows where NO GT lane has a point (often the top rows) are dropped, and the official
    per-lane accuracy divides by ALL h_samples, so the two differ unless some GT lane spans every
    row. GT lanes with interior -2 gaps get interpolated across the gap in either mode.
    """

    full_state_update = False
    is_differentiable = False

    def __init__(self, pixel_thresh: float = 20, pt_thresh: float = 0.85, **kwargs) -> None:
        super().__init__(**kwargs)
        self.pixel_thresh = pixel_thresh
        self.pt_thresh = pt_thresh
        for name in ("acc_sum", "fp_sum", "fn_sum", "num_images"):
            self.add_state(name, default=torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")

    def update(
        self,
        preds: Sequence[Sequence[np.ndarray]],
        targets: Sequence[Sequence[np.ndarray]],
        h_samples: Sequence[np.ndarray] | np.ndarray | None = None,
    ) -> None:
        """Add a batch: preds[i] and targets[i] are image i's lanes, each an (N, 2) pixel array."""
        if len(preds) != len(targets):
            raise ValueError(f"preds has {len(preds)} images but targets has {len(targets)}")
        if h_samples is not None and isinstance(h_samples, np.ndarray) and h_samples.ndim == 1:
            h_samples = [h_samples] * len(targets)
        if h_samples is not None and len(h_samples) != len(targets):
            raise ValueError(f"h_samples has {len(h_samples)} entries but targets has {len(targets)}")
        acc = fp = fn = 0.0
        for i, (pred_lanes, gt_lanes) in enumerate(zip(preds, targets)):
            gts = [_as_np_lane(lane) for lane in gt_lanes]
            prs = [_as_np_lane(lane) for lane in pred_lanes]
            if h_samples is None:
                ys = np.unique(np.concatenate([g[:, 1] for g in gts])) if gts else np.zeros(0)
            else:
                ys = np.asarray(h_samples[i], dtype=np.float64).reshape(-1)
            a, p, n = tusimple_lane_scores(prs, gts, ys, self.pixel_thresh, self.pt_thresh)
            acc += a
            fp += p
            fn += n
        self.acc_sum += acc
        self.fp_sum += fp
        self.fn_sum += fn
        self.num_images += len(targets)

    def compute(self) -> dict[str, torch.Tensor]:
        """{"Accuracy", "FP", "FN", "F1"} as float64 scalar tensors."""
        out = tusimple_summary(
            float(self.acc_sum), float(self.fp_sum), float(self.fn_sum), int(round(float(self.num_images)))
        )
        return {k: torch.tensor(v, dtype=torch.float64) for k, v in out.items()}


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
        out.append((lineno, obj))
    return out


def _rows(value, path: Path, lineno: int, what: str) -> np.ndarray:
    try:
        lanes = [np.asarray(lane, dtype=np.float64) for lane in value]
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}:{lineno}: {what} must be lists of numbers ({e})") from e
    return lanes


def evaluate_tusimple_files(
    pred_path: str | Path, gt_path: str | Path, pixel_thresh: float = 20, pt_thresh: float = 0.85
) -> dict:
    """Official file-level evaluation (bench_one_submit): JSON-lines preds vs GT, keyed by raw_file.

    Every GT image needs exactly one prediction and every prediction a GT image (as officially).
    ``run_time`` is accepted but ignored (no run-time penalty). Returns {"Accuracy","FP","FN","F1"}.
    """
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
    acc = fp = fn = 0.0
    for raw, (gt_line, gt) in gts.items():
        if raw not in preds:
            raise ValueError(f"no prediction in {pred_path} for GT image raw_file {raw!r} ({gt_path}:{gt_line})")
        pred_line, pred = preds[raw]
        ys = np.asarray(gt["h_samples"], dtype=np.float64).reshape(-1)
        gt_rows = _rows(gt["lanes"], gt_path, gt_line, "GT lanes")
        for j, lane in enumerate(gt_rows):
            if lane.shape != ys.shape:
                raise ValueError(
                    f"{gt_path}:{gt_line}: GT lane {j} has {lane.size} x values, h_samples has {ys.size}"
                )
        pred_rows = _rows(pred["lanes"], pred_path, pred_line, "predicted lanes")
        for j, lane in enumerate(pred_rows):
            if lane.shape != ys.shape:
                raise ValueError(
                    f"{pred_path}:{pred_line}: Format of lanes error: lane {j} of {raw!r} has "
                    f"{lane.size} x values but h_samples has {ys.size}"
                )
        a, p, n = tusimple_image_scores(
            np.stack(pred_rows) if pred_rows else np.zeros((0, ys.size)),
            np.stack(gt_rows) if gt_rows else np.zeros((0, ys.size)),
            ys,
            pixel_thresh,
            pt_thresh,
        )
        acc += a
        fp += p
        fn += n
    return tusimple_summary(acc, fp, fn, len(gts))

