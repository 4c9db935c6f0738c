"""TuSimple metric vs a slow, literal re-statement of the official LaneEval procedure."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lanevil_train.lanes import TUSIMPLE_H_SAMPLES, rows_to_lane
from lanevil_train.metrics import TuSimpleMetric, tusimple_image_scores, tusimple_summary

# --------------------------------------------------------------------------------------------
# Reference: the official tusimple-benchmark evaluate/lane.py, step by step, in plain Python.
# --------------------------------------------------------------------------------------------


def ref_slope(xs: list[float], ys: list[float]) -> float:
    """Ordinary least-squares slope of x on y by the textbook formulas."""
    n = len(xs)
    my = sum(ys) / n
    mx = sum(xs) / n
    num = sum((ys[i] - my) * (xs[i] - mx) for i in range(n))
    den = sum((ys[i] - my) ** 2 for i in range(n))
    return num / den


def ref_get_angle(xs: list[float], y_samples: list[float]) -> float:
    keep_x = [x for x in xs if x >= 0]
    keep_y = [y for x, y in zip(xs, y_samples) if x >= 0]
    if len(keep_x) > 1:
        return math.atan(ref_slope(keep_x, keep_y))
    return 0.0


def ref_line_accuracy(pred: list[float], gt: list[float], thresh: float) -> float:
    pred = [p if p >= 0 else -100 for p in pred]
    gt = [g if g >= 0 else -100 for g in gt]
    hits = 0.0
    for p, g in zip(pred, gt):
        if abs(p - g) < thresh:
            hits += 1.0
    return hits / len(gt)


def ref_bench(pred: list[list[float]], gt: list[list[float]], y_samples: list[float]):
    if any(len(p) != len(y_samples) for p in pred):
        raise Exception("Format of lanes error.")
    if len(gt) + 2 < len(pred):  # (the run_time > 200 rule is not reproduced)
        return 0.0, 0.0, 1.0
    threshs = [20 / math.cos(ref_get_angle(x_gts, y_samples)) for x_gts in gt]
    line_accs = []
    fn = 0.0
    matched = 0.0
    for x_gts, thresh in zip(gt, threshs):
        accs = [ref_line_accuracy(x_preds, x_gts, thresh) for x_preds in pred]
        max_acc = max(accs) if len(accs) > 0 else 0.0
        if max_acc < 0.85:
            fn += 1
        else:
            matched += 1
        line_accs.append(max_acc)
    fp = len(pred) - matched
    if len(gt) > 4 and fn > 0:
        fn -= 1
    s = sum(line_accs)
    if len(gt) > 4:
        s -= min(line_accs)
    return (
        s / max(min(4.0, len(gt)), 1.0),
        fp / len(pred) if len(pred) > 0 else 0.0,
        fn / max(min(len(gt), 4.0), 1.0),
    )


def ref_dataset(images) -> dict:
    """bench_one_submit's means + CLRNet's F1 formula."""
    acc = fp = fn = 0.0
    for pred, gt, ys in images:
        a, p, n = ref_bench(pred, gt, ys)
        acc += a
        fp += p
        fn += n
    num = len(images)
    fp, fn = fp / num, fn / num
    tp = 1 - fp
    precision = tp / (tp + fp)
    recall = tp / (tp + fn)
    f1 = 2 * precision * recall / (precision + recall)
    return {"Accuracy": acc / num, "FP": fp, "FN": fn, "F1": f1}


# --------------------------------------------------------------------------------------------
# Random TuSimple-like images.
# --------------------------------------------------------------------------------------------


def random_image(rng: np.random.Generator):
    """(pred rows, gt rows, h_samples) as lists, with gaps, steep/vertical lanes, near-miss preds."""
    if rng.random() < 0.5:
        ys = TUSIMPLE_H_SAMPLES.copy()
    else:
        ys = np.sort(rng.choice(np.arange(100, 720), size=int(rng.integers(5, 30)), replace=False)).astype(float)
    h = len(ys)
    n_gt = int(rng.integers(0, 7))
    n_pred = int(rng.integers(0, 9))
    gts = []
    for _ in range(n_gt):
        kind = rng.random()
        x0 = rng.uniform(100, 1200)
        if kind < 0.2:
            xs = np.full(h, round(x0))  # vertical: slope exactly 0
        elif kind < 0.4:
            xs = x0 + rng.choice([-1, 1]) * rng.uniform(1.5, 4.0) * (ys - ys.mean())  # steep
        else:
            xs = x0 + rng.uniform(-0.8, 0.8) * (ys - ys.mean()) + rng.normal(0, 3, h)
        xs = np.round(xs)
        lo, hi = sorted(rng.integers(0, h + 1, size=2))
        xs[:lo] = -2
        xs[hi:] = -2
        if rng.random() < 0.2:  # interior gaps, single points
            xs[rng.random(h) < 0.2] = -2
        xs[xs < 0] = -2
        gts.append(xs)
    preds = []
    for j in range(n_pred):
        if gts and rng.random() < 0.75:
            base = gts[int(rng.integers(0, len(gts)))].copy()
            valid = base >= 0
            r = rng.random()
            if r < 0.3:  # near the 20 px boundary (either side, away from float ties)
                off = rng.choice([-1, 1]) * (20 + rng.choice([-1, 1]) * rng.uniform(1e-6, 0.5))
                off = off * np.where(rng.random(h) < 0.5, 1.0, 0.2)
            elif r < 0.6:
                off = rng.normal(0, 12, h)
            else:
                off = rng.normal(0, 40, h)
            xs = np.where(valid, base + off, -2.0)
            if rng.random() < 0.3:  # pred extends/shrinks its span
                xs[rng.random(h) < 0.15] = -2
            xs[(xs < 0)] = -2
        else:
            xs = rng.uniform(-50, 1300, h)
            xs[xs < 0] = -2
        preds.append(xs)
    return preds, gts, ys


def as_array(rows, h):
    return np.array(rows, dtype=np.float64).reshape(len(rows), h)


def test_random_images_match_reference_per_image_and_dataset():
    rng = np.random.default_rng(1234)
    images = [random_image(rng) for _ in range(600)]
    acc = fp = fn = 0.0
    for preds, gts, ys in images:
        ours = tusimple_image_scores(as_array(preds, len(ys)), as_array(gts, len(ys)), ys)
        ref = ref_bench([list(p) for p in preds], [list(g) for g in gts], list(ys))
        assert ours == pytest.approx(ref, abs=1e-9), (preds, gts)
        acc, fp, fn = acc + ours[0], fp + ours[1], fn + ours[2]
    ref = ref_dataset([([list(p) for p in pr], [list(g) for g in gt], list(ys)) for pr, gt, ys in images])
    ours = tusimple_summary(acc, fp, fn, len(images))
    for key in ("Accuracy", "FP", "FN", "F1"):
        assert ours[key] == pytest.approx(ref[key], abs=1e-9)
    # the random cases really exercise the rules (not all zeros / all ones)
    scores = np.array([tusimple_image_scores(as_array(p, len(y)), as_array(g, len(y)), y) for p, g, y in images])
    assert 0.2 < scores[:, 0].mean() < 0.9
    assert (scores[:, 2] == 1.0).sum() > 20 and (scores[:, 1] == 0.0).sum() > 20
    assert np.any((scores[:, 0] > 0) & (scores[:, 0] < 1))


def test_hand_computed_image():
    ys = np.arange(10, 210, 10.0)  # 20 rows
    gt = np.stack([np.full(20, 100.0), np.full(20, 300.0)])
    pred = np.stack([np.full(20, 110.0), np.full(20, 500.0), np.full(20, 900.0)])
    acc, fp, fn = tusimple_image_scores(pred, gt, ys)
    # lane 0 matched (acc 1), lane 1 missed (acc 0); 3 preds - 1 matched = 2 fp
    assert (acc, fp, fn) == (0.5, 2 / 3, 0.5)


def test_vertical_lane_threshold_is_strictly_20px():
    ys = np.arange(10, 210, 10.0)
    gt = np.full((1, 20), 400.0)
    assert tusimple_image_scores(gt + 19.999, gt, ys)[0] == 1.0
    assert tusimple_image_scores(gt + 20.0, gt, ys)[0] == 0.0


def test_sloped_lane_threshold_is_20_over_cos():
    ys = np.arange(10, 210, 10.0)
    gt = (100 + 1.0 * ys)[None]  # 45 degrees: threshold 20 * sqrt(2) = 28.28
    assert tusimple_image_scores(gt + 28.2, gt, ys)[0] == 1.0
    assert tusimple_image_scores(gt + 28.3, gt, ys)[0] == 0.0


def test_pt_thresh_boundary_is_inclusive():
    ys = np.arange(10, 210, 10.0)  # 20 rows: 17/20 = 0.85 exactly
    gt = np.full((1, 20), 400.0)
    pred = gt.copy()
    pred[0, :3] = 700  # 17 of 20 hit
    assert tusimple_image_scores(pred, gt, ys) == (0.85, 0.0, 0.0)
    pred[0, 3] = 700  # 16 of 20
    assert tusimple_image_scores(pred, gt, ys) == (pytest.approx(0.8), 1.0, 1.0)


def test_invalid_points_agree_with_each_other():
    ys = np.arange(10, 210, 10.0)
    gt = np.full((1, 20), 400.0)
    gt[0, :10] = -2
    pred = np.full((1, 20), -2.0)
    pred[0, 10:] = 405
    assert tusimple_image_scores(pred, gt, ys)[0] == 1.0  # both -100 on the first 10 rows
    pred[0, :10] = 50  # pred claims points where GT has none: 10 misses
    assert tusimple_image_scores(pred, gt, ys)[0] == 0.5


def test_too_many_predictions_early_exit():
    ys = np.arange(10, 210, 10.0)
    gt = np.stack([np.full(20, 100.0 * (i + 1)) for i in range(2)])
    four = np.stack([np.full(20, 100.0 * (i + 1)) for i in range(4)])
    assert tusimple_image_scores(four, gt, ys) == (1.0, 0.5, 0.0)  # 2 + 2 < 4 is false
    five = np.concatenate([four, np.full((1, 20), 900.0)])
    assert tusimple_image_scores(five, gt, ys) == (0.0, 0.0, 1.0)


def test_more_than_four_gt_lanes_forgives_one():
    ys = np.arange(10, 210, 10.0)
    gt = np.stack([np.full(20, 100.0 * (i + 1)) for i in range(5)])
    pred = gt[:4].copy()  # lane 5 missed: fn 1 -> 0, worst acc dropped
    assert tusimple_image_scores(pred, gt, ys) == (1.0, 0.0, 0.0)
    pred = gt[:3].copy()  # two missed: fn 2 -> 1, over min(5, 4)
    assert tusimple_image_scores(pred, gt, ys) == (0.75, 0.0, 0.25)


def test_image_without_gt_lanes():
    ys = TUSIMPLE_H_SAMPLES
    no_gt = np.zeros((0, len(ys)))
    assert tusimple_image_scores(np.zeros((0, len(ys))), no_gt, ys) == (0.0, 0.0, 0.0)
    assert tusimple_image_scores(np.full((2, len(ys)), 300.0), no_gt, ys) == (0.0, 1.0, 0.0)
    assert tusimple_image_scores(np.full((3, len(ys)), 300.0), no_gt, ys) == (0.0, 0.0, 1.0)
    assert ref_bench([], [], list(ys)) == (0.0, 0.0, 0.0)


def test_format_error_on_wrong_pred_length():
    ys = np.arange(10, 210, 10.0)
    with pytest.raises(ValueError, match="Format of lanes error"):
        tusimple_image_scores(np.zeros((1, 19)), np.zeros((1, 20)), ys)


def test_summary_f1_and_degenerate_cases():
    out = tusimple_summary(9.0, 1.0, 2.0, 10)  # acc .9, fp .1, fn .2
    p, r = 0.9, 0.9 / 1.1
    assert out == pytest.approx({"Accuracy": 0.9, "FP": 0.1, "FN": 0.2, "F1": 2 * p * r / (p + r)})
    assert tusimple_summary(0.0, 3.0, 0.0, 3)["F1"] == 0.0  # CLRNet would divide by zero
    with pytest.raises(ValueError, match="num_images"):
        tusimple_summary(0, 0, 0, 0)


def _rows_to_lanes(rows, ys):
    return [rows_to_lane(r, ys) for r in rows if np.any(np.asarray(r) >= 0)]


def _contiguous_image(rng):
    """Images whose lanes are contiguous runs (no interior gaps), so pixel lanes are exact rows."""
    ys = TUSIMPLE_H_SAMPLES
    gts, preds = [], []
    for _ in range(int(rng.integers(0, 6))):
        xs = np.round(rng.uniform(100, 1200) + rng.uniform(-2, 2) * (ys - 400))
        lo, hi = sorted(rng.integers(0, len(ys) - 1, size=2))
        xs[:lo] = -2
        xs[hi + 2 :] = -2
        xs[xs < 0] = -2
        if np.count_nonzero(xs >= 0) >= 2:
            gts.append(xs)
    for _ in range(int(rng.integers(0, 7))):
        if gts and rng.random() < 0.7:
            base = gts[int(rng.integers(0, len(gts)))]
            xs = np.where(base >= 0, np.maximum(base + rng.normal(0, 10, len(ys)), 0.0), -2.0)
        else:  # a straight line: any off-image part is at one end, so the run stays contiguous
            xs = np.round(rng.uniform(0, 1280) + rng.uniform(-1, 1) * (ys - 400))
            xs[xs < 0] = -2
        if np.count_nonzero(xs >= 0) >= 2:
            preds.append(xs)
    return preds, gts, ys


def test_metric_matches_reference_and_ddp_style_merge():
    rng = np.random.default_rng(7)
    images = [_contiguous_image(rng) for _ in range(120)]
    preds = [_rows_to_lanes(p, ys) for p, g, ys in images]
    gts = [_rows_to_lanes(g, ys) for p, g, ys in images]
    hs = [ys for _, _, ys in images]
    ref = ref_dataset([([list(p) for p in pr], [list(g) for g in gt], list(ys)) for pr, gt, ys in images])

    whole = TuSimpleMetric()
    whole.update(preds[:50], gts[:50], hs[:50])
    whole.update(preds[50:], gts[50:], hs[50:])
    out = whole.compute()
    assert set(out) == {"Accuracy", "FP", "FN", "F1"}
    for k in out:
        assert float(out[k]) == pytest.approx(ref[k], abs=1e-9)

    # two "ranks" on halves; a sum-reduction of their states equals the single instance
    a, b = TuSimpleMetric(), TuSimpleMetric()
    a.update(preds[:70], gts[:70], hs[:70])
    b.update(preds[70:], gts[70:], hs[70:])
    from torchmetrics.utilities.data import dim_zero_sum

    assert a._reductions == {n: dim_zero_sum for n in ("acc_sum", "fp_sum", "fn_sum", "num_images")}
    for name, reduce_fx in a._reductions.items():  # what sync() does with the gathered states
        setattr(a, name, reduce_fx(torch.stack([getattr(a, name), getattr(b, name)])))
    merged = a.compute()
    c, d = TuSimpleMetric(), TuSimpleMetric()
    c.update(preds[:33], gts[:33], hs[:33])
    d.update(preds[33:], gts[33:], hs[33:])
    c.merge_state(d)
    assert float(c.compute()["F1"]) == pytest.approx(float(out["F1"]), abs=1e-12)
    for k in out:
        assert float(merged[k]) == pytest.approx(float(out[k]), abs=1e-12)
    assert float(a.num_images) == 120


def test_metric_h_samples_from_gt_equals_explicit_rows_for_tusimple_lanes():
    rng = np.random.default_rng(3)
    images = [_contiguous_image(rng) for _ in range(40)]
    images = [im for im in images if im[1]]  # rows from GT need GT lanes to be all rows
    preds = [_rows_to_lanes(p, ys) for p, g, ys in images]
    gts = [_rows_to_lanes(g, ys) for p, g, ys in images]
    m1, m2 = TuSimpleMetric(), TuSimpleMetric()
    m1.update(preds, gts, None)
    # equivalent explicit rows: the union of the GT lanes' ys
    m2.update(preds, gts, [np.unique(np.concatenate([g[:, 1] for g in gt])) for gt in gts])
    assert {k: float(v) for k, v in m1.compute().items()} == {k: float(v) for k, v in m2.compute().items()}


def test_metric_accepts_torch_lanes_and_image_without_gt():
    m = TuSimpleMetric()
    lane = torch.tensor([[300.0, 710.0], [320.0, 160.0]])
    m.update([[lane]], [[lane.numpy()]], [TUSIMPLE_H_SAMPLES])
    m.update([[lane]], [[]], None)  # no GT: accuracy 0, fp 1, fn 0 (official arithmetic)
    out = m.compute()
    assert float(out["Accuracy"]) == 0.5 and float(out["FP"]) == 0.5 and float(out["FN"]) == 0.0


def test_metric_rejects_mismatched_batch():
    with pytest.raises(ValueError, match="targets has 1"):
        TuSimpleMetric().update([[], []], [[]])


def test_steep_lane_invalid_pred_point_counts_near_x0_as_official():
    # slope dx/dy = 10 -> threshold 20/cos(atan(10)) = 201 px; the official -100 fill makes a
    # missing pred point "hit" every GT point with x < 101 (|x - (-100)| < 201)
    ys = np.arange(100, 120, 1.0)  # 20 rows
    gt = (10.0 * (ys - 100))[None]  # x = 0, 10, ..., 190
    pred = np.full((1, 20), -2.0)
    acc = tusimple_image_scores(pred, gt, ys)[0]
    assert acc == pytest.approx(11 / 20)  # x = 0..100 -> 11 rows
    assert acc == pytest.approx(ref_bench([list(pred[0])], [list(gt[0])], list(ys))[0])


def test_x_equal_zero_is_a_valid_point_in_the_angle_fit():
    ys = np.arange(10, 210, 10.0)
    gt = np.full((1, 20), 400.0)
    gt[0, 0] = 0.0  # valid (x >= 0): tilts the fitted line, widening the threshold beyond 20
    pred = gt + 22.0  # threshold with the x=0 point: 20 / cos(atan(0.571)) = 23.03
    expected = ref_bench([list(pred[0])], [list(gt[0])], list(ys))
    assert expected[0] == 1.0  # sanity: 22 px is a hit only because x=0 entered the fit
    assert tusimple_image_scores(pred, gt, ys) == pytest.approx(expected)
