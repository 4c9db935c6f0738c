"""A CurveLanes image's evaluation record counts its CULane-style TP/FP/FN with the CurveLanes procedure."""

from __future__ import annotations

import numpy as np

from lanevil_train.evaluation.lane_records import lane_record
from tests.metrics.test_curvelanes import SIZE, _vertical


def test_an_evaluation_record_of_a_curvelanes_image_uses_its_metric():
    gt = [_vertical(112.5), _vertical(150.5)]
    # 22.9 px off, 2 evaluation columns: a CurveLanes hit; CULane's procedure (30 px at 1640 wide, so 47 px lanes at
    # 2560) gives IoU ~ (47 - 23) / (47 + 23) = 0.34, a miss; and an exact lane
    pred = [_vertical(114.5), _vertical(150.5)]
    meta = {"case_id": "valid/images/a.jpg", "height": SIZE[0], "width": SIZE[1],
            "h_samples": np.arange(400.0, 1440.0, 40.0)}
    assert [lane_record(pred, gt, meta)[k] for k in ("culane_tp", "culane_fp", "culane_fn")] == [1, 1, 1]
    meta["culane_metric"] = "curvelanes"
    assert [lane_record(pred, gt, meta)[k] for k in ("culane_tp", "culane_fp", "culane_fn")] == [2, 0, 0]
