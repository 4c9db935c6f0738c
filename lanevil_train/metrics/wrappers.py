"""torchmetrics wrappers of the lane scores: TuSimpleMetric and CULaneMetric (sum states, DDP-safe).

The scoring itself is the plain numpy code of ``tusimple.py`` / ``culane.py``; this module is the only
one under ``lanevil_train.metrics`` that imports torch, so the file-scoring commands never load it.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from torchmetrics import Metric

from lanevil_train.lanes import check_row_sampling
from lanevil_train.metrics.culane import (
    MF1_THRESHOLDS,
    culane_image_counts_multi,
    culane_leaderboard_scores,
    culane_summary,
)
from lanevil_train.metrics.tusimple import tusimple_lane_scores, tusimple_summary

__all__ = ["TuSimpleMetric", "CULaneMetric"]

_COUNT_STATES = ("tp_count", "fp_count", "fn_count")  # TuSimpleMetric's lane counts (F1_count)


def _to_numpy(lane: object) -> object:
    """A tensor lane (on any device) as a numpy array; anything else unchanged."""
    if isinstance(lane, torch.Tensor):
        return lane.detach().cpu().numpy()
    return lane


def _as_np_lane(lane: object) -> np.ndarray:
    """One (N, 2) float64 pixel lane from an array, list or tensor; raises on another shape."""
    arr = np.asarray(_to_numpy(lane), dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"a lane must be an (N, 2) array of (x, y) pixels, got shape {arr.shape}")
    return arr


class TuSimpleMetric(Metric):
    """TuSimple Accuracy / FP / FN / F1 and the lane-count F1_count over decoded lanes (pixels); DDP-safe sum
    states (the per-image sums and the TP / FP / FN lane counts, each summed over processes).

    Each image's lanes are sampled at its h_samples with ``lanes_to_rows`` (the predicted lanes as
    ``row_sampling`` reads them, lanes.ROW_SAMPLINGS, default linear interpolation, -2 outside a lane's span; the
    ground truth linearly); pass the GT file's h_samples to get the official
    score. With ``h_samples=None`` the rows are the sorted unique y values of that image's GT
    points. TuSimple GT points already lie on its h_samples, so every GT point is kept exactly,
    but rows where NO GT lane has a point (often the top rows) are dropped, and the official
    per-lane accuracy divides by ALL h_samples, so the two differ unless some GT lane spans every
    row. GT lanes with interior -2 gaps get interpolated across the gap in either mode.
    """

    full_state_update = False
    is_differentiable = False

    def __init__(self, pixel_thresh: float = 20, pt_thresh: float = 0.85, row_sampling: str = "linear",
                 **kwargs) -> None:
        super().__init__(**kwargs)
        self.pixel_thresh = pixel_thresh
        self.pt_thresh = pt_thresh
        self.row_sampling = check_row_sampling(row_sampling, "row_sampling")
        for name in ("acc_sum", "fp_sum", "fn_sum", "num_images"):
            self.add_state(name, default=torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")
        for name in _COUNT_STATES:  # F1_count's lanes: integers, so sums over processes are exact
            self.add_state(name, default=torch.tensor(0, dtype=torch.long), dist_reduce_fx="sum")

    def update(
        self,
        preds: Sequence[Sequence[np.ndarray]],
        targets: Sequence[Sequence[np.ndarray]],
        h_samples: Sequence[np.ndarray] | np.ndarray | None = None,
        heights: Sequence[float] | None = None,
    ) -> None:
        """Add a batch: preds[i] and targets[i] are image i's lanes, each an (N, 2) pixel array; heights[i] the
        image's height (needed by row_sampling "spline" only)."""
        if len(preds) != len(targets):
            raise ValueError(f"preds has {len(preds)} images but targets has {len(targets)}")
        if h_samples is not None and isinstance(h_samples, np.ndarray) and h_samples.ndim == 1:
            h_samples = [h_samples] * len(targets)
        if h_samples is not None and len(h_samples) != len(targets):
            raise ValueError(f"h_samples has {len(h_samples)} entries but targets has {len(targets)}")
        acc = fp = fn = 0.0
        counts = [0, 0, 0]
        for i, (pred_lanes, gt_lanes) in enumerate(zip(preds, targets)):
            gts = [_as_np_lane(lane) for lane in gt_lanes]
            prs = [_as_np_lane(lane) for lane in pred_lanes]
            if h_samples is None:
                ys = np.unique(np.concatenate([g[:, 1] for g in gts])) if gts else np.zeros(0)
            else:
                ys = np.asarray(h_samples[i], dtype=np.float64).reshape(-1)
            height = None if heights is None else heights[i]
            a, p, n, *lanes = tusimple_lane_scores(prs, gts, ys, self.pixel_thresh, self.pt_thresh, with_counts=True,
                                                   row_sampling=self.row_sampling, height=height)
            acc += a
            fp += p
            fn += n
            counts = [c + k for c, k in zip(counts, lanes)]
        self.acc_sum += acc
        self.fp_sum += fp
        self.fn_sum += fn
        self.num_images += len(targets)
        for name, count in zip(_COUNT_STATES, counts):
            setattr(self, name, getattr(self, name) + count)

    def compute(self) -> dict[str, torch.Tensor]:
        """{"Accuracy", "FP", "FN", "F1", "F1_count"} as float64 scalar tensors (tusimple_summary; the lane counts
        stay in the states tp_count / fp_count / fn_count, out of the logged scores)."""
        out = tusimple_summary(
            float(self.acc_sum), float(self.fp_sum), float(self.fn_sum), int(round(float(self.num_images))),
            counts=tuple(int(getattr(self, name)) for name in _COUNT_STATES),
        )
        return {k: torch.tensor(out[k], dtype=torch.float64) for k in ("Accuracy", "FP", "FN", "F1", "F1_count")}




class CULaneMetric(Metric):
    """Streaming CULane scores: TP/FP/FN at ``iou_threshold`` and the TP at each mF1 threshold (F1@50, F1@75,
    mF1), summed over images (sum-reduced across processes); one matching per image for all thresholds."""

    full_state_update = False
    higher_is_better = True

    def __init__(self, width: int = 1640, height: int = 590, lane_width: int = 30, iou_threshold: float = 0.5,
                 **kwargs: object) -> None:
        super().__init__(**kwargs)
        self.width, self.height, self.lane_width, self.iou_threshold = width, height, lane_width, iou_threshold
        self.thresholds = tuple(dict.fromkeys((*MF1_THRESHOLDS, iou_threshold)))
        for name in ("tp", "fp", "fn", "num_images", "num_pred", "num_gt"):
            self.add_state(name, default=torch.tensor(0, dtype=torch.long), dist_reduce_fx="sum")
        self.add_state("tp_at", default=torch.zeros(len(self.thresholds), dtype=torch.long), dist_reduce_fx="sum")

    def update(self, preds: Sequence[Sequence[object]], targets: Sequence[Sequence[object]]) -> None:
        """Add the counts of a batch: ``preds``/``targets`` are per-image lists of (N, 2) pixel lanes."""
        if len(preds) != len(targets):
            raise ValueError(f"preds has {len(preds)} images but targets has {len(targets)}")
        tp_at = [0] * len(self.thresholds)
        n_pred = n_gt = 0
        for p, g in zip(preds, targets):
            counts = culane_image_counts_multi([_to_numpy(lane) for lane in p], [_to_numpy(lane) for lane in g],
                                               self.width, self.height, self.lane_width, self.thresholds)
            tp_at = [total + tp for total, (tp, _, _) in zip(tp_at, counts)]
            n_pred, n_gt = n_pred + len(p), n_gt + len(g)
        tp = tp_at[self.thresholds.index(self.iou_threshold)]
        self.tp += tp
        self.fp += n_pred - tp
        self.fn += n_gt - tp
        self.num_images += len(targets)
        self.num_pred += n_pred
        self.num_gt += n_gt
        self.tp_at += torch.tensor(tp_at, dtype=torch.long)

    def compute(self) -> dict:
        """``culane_summary`` of the counts at ``iou_threshold``, the image count, and F1@50, F1@75, mF1: the keys
        of ``evaluate_culane_dirs`` (without categories)."""
        n_pred, n_gt = int(self.num_pred), int(self.num_gt)
        totals = {t: (int(tp), n_pred - int(tp), n_gt - int(tp)) for t, tp in zip(self.thresholds, self.tp_at)}
        return {**culane_summary(int(self.tp), int(self.fp), int(self.fn)), "images": int(self.num_images),
                **culane_leaderboard_scores(totals)}
