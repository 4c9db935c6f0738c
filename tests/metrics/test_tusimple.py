"""TuSimple metric vs a slow, literal re-statement of the official LaneEval procedure."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.optimize import linear_sum_assignment

from lanevil_train.lanes import TUSIMPLE_H_SAMPLES, rows_to_lane
from lanevil_train.metrics import TuSimpleMetric, tusimple_count_f1, tusimple_image_scores, tusimple_summary

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


def ref_counts(pred: list[list[float]], gt: list[list[float]], y_samples: list[float]) -> tuple[int, int, int]:
    """F1_count's (TP, FP, FN) of one image: a (pred, GT) pair matches at the official line accuracy >= 0.85; TP is
    a maximum one-to-one matching of such pairs (scipy's assignment on the 0/1 match matrix)."""
    match = np.array([[ref_line_accuracy(p, g, 20 / math.cos(ref_get_angle(g, y_samples))) >= 0.85 for p in pred]
                      for g in gt], dtype=float).reshape(len(gt), len(pred))
    rows, cols = linear_sum_assignment(match, maximize=True)
    tp = int(match[rows, cols].sum())
    return tp, len(pred) - tp, len(gt) - tp


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
    same_matched = fewer = 0
    for preds, gts, ys in images:
        ours = tusimple_image_scores(as_array(preds, len(ys)), as_array(gts, len(ys)), ys)
        ref = ref_bench([list(p) for p in preds], [list(g) for g in gts], list(ys))
        assert ours == pytest.approx(ref, abs=1e-9), (preds, gts)
        acc, fp, fn = acc + ours[0], fp + ours[1], fn + ours[2]
        both = tusimple_image_scores(as_array(preds, len(ys)), as_array(gts, len(ys)), ys, with_counts=True)
        assert both[:3] == ours  # the counts change nothing of the official scores
        counts = ref_counts([list(p) for p in preds], [list(g) for g in gts], list(ys))
        assert both[3:] == counts and all(type(c) is int for c in both[3:])
        if len(gts) + 2 >= len(preds) and len(gts) <= 4:  # no official penalty or forgiveness
            official_matched = len(gts) - round(ours[2] * max(len(gts), 1))
            assert counts[0] <= official_matched  # fewer only where one pred is the match of several GT lanes
            same_matched += counts[0] == official_matched
            fewer += counts[0] < official_matched
    ref = ref_dataset([([list(p) for p in pr], [list(g) for g in gt], list(ys)) for pr, gt, ys in images])
    ours = tusimple_summary(acc, fp, fn, len(images))
    for key in ("Accuracy", "FP", "FN", "F1"):
        assert ours[key] == pytest.approx(ref[key], abs=1e-9)
    # the random cases really exercise the rules (not all zeros / all ones)
    scores = np.array([tusimple_image_scores(as_array(p, len(y)), as_array(g, len(y)), y) for p, g, y in images])
    assert 0.2 < scores[:, 0].mean() < 0.9
    assert (scores[:, 2] == 1.0).sum() > 20 and (scores[:, 1] == 0.0).sum() > 20
    assert np.any((scores[:, 0] > 0) & (scores[:, 0] < 1))
    assert same_matched > 200 and fewer < same_matched / 10, (same_matched, fewer)


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
    assert set(out) == {"Accuracy", "FP", "FN", "F1", "F1_count"}
    for k in ref:
        assert float(out[k]) == pytest.approx(ref[k], abs=1e-9)
    tp, fp, fn = (sum(c) for c in zip(*(ref_counts([list(r) for r in pr], [list(r) for r in gt], list(ys))
                                         for pr, gt, ys in images)))
    assert (int(whole.tp_count), int(whole.fp_count), int(whole.fn_count)) == (tp, fp, fn)
    assert float(out["F1_count"]) == pytest.approx(2 * tp / (2 * tp + fp + fn), abs=1e-12)
    assert 0 < fp and 0 < fn and 0.3 < float(out["F1_count"]) < 0.95

    # two "ranks" on halves; a sum-reduction of their states equals the single instance
    a, b = TuSimpleMetric(), TuSimpleMetric()
    a.update(preds[:70], gts[:70], hs[:70])
    b.update(preds[70:], gts[70:], hs[70:])
    from torchmetrics.utilities.data import dim_zero_sum

    assert a._reductions == {n: dim_zero_sum for n in ("acc_sum", "fp_sum", "fn_sum", "num_images", "tp_count",
                                                       "fp_count", "fn_count")}
    assert a.tp_count.dtype == torch.long and 0 < int(a.tp_count) < tp  # each rank holds its own part
    for name, reduce_fx in a._reductions.items():  # what sync() does with the gathered states
        setattr(a, name, reduce_fx(torch.stack([getattr(a, name), getattr(b, name)])))
    merged = a.compute()
    c, d = TuSimpleMetric(), TuSimpleMetric()
    c.update(preds[:33], gts[:33], hs[:33])
    d.update(preds[33:], gts[33:], hs[33:])
    c.merge_state(d)
    assert float(c.compute()["F1"]) == pytest.approx(float(out["F1"]), abs=1e-12)
    assert float(c.compute()["F1_count"]) == float(out["F1_count"])
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


# --------------------------------------------------------------------------------------------
# F1_count: TP / FP / FN counted over lanes (not official; beside the papers' F1).
# --------------------------------------------------------------------------------------------

ROWS = np.arange(10, 210, 10.0)  # 20 rows


def _vertical(*xs: float) -> np.ndarray:
    """Vertical lanes at the given x over all 20 rows, as (L, 20) rows."""
    return np.array([np.full(20, float(x)) for x in xs]).reshape(len(xs), 20)


def _dataset(images) -> dict:
    """tusimple_summary with counts of (pred rows, gt rows) images on ROWS."""
    totals = np.zeros(6)
    for pred, gt in images:
        totals += tusimple_image_scores(pred, gt, ROWS, with_counts=True)
    return tusimple_summary(*totals[:3], len(images), counts=tuple(int(c) for c in totals[3:]))


def test_silent_model_reads_zero_while_the_papers_f1_reads_two_thirds():
    gt = _vertical(100, 300, 500, 700)
    out = _dataset([(_vertical(), gt), (_vertical(), gt[:2])])
    assert out["F1"] == pytest.approx(2 / 3)  # FP 0, FN 1 -> tp 1, P 1, R 1/2 (CLRNet's formula)
    assert (out["TP_count"], out["FP_count"], out["FN_count"]) == (0, 0, 6)
    assert out["F1_count"] == 0.0


def test_perfect_model_reads_one():
    gt = _vertical(100, 300, 500, 700)
    out = _dataset([(gt + 5, gt), (gt[:2] - 5, gt[:2])])
    assert out["F1"] == 1.0 and out["F1_count"] == 1.0
    assert (out["TP_count"], out["FP_count"], out["FN_count"]) == (6, 0, 0)


def test_mixed_case_by_hand():
    """Image 1: 2 GT, both found, plus a false positive; image 2: 2 GT, one found. Lanes: TP 3, FP 1, FN 1 ->
    F1_count = 6 / 8 = 0.75 (the mean of per-image F1s would be (0.8 + 2/3) / 2). The papers' F1: FP (1/3 + 0) / 2
    = 1/6, FN (0 + 1/2) / 2 = 1/4 -> tp 5/6, P 5/6, R 10/13 -> F1 0.8."""
    gt = _vertical(100, 300)
    out = _dataset([(_vertical(105, 290, 900), gt), (_vertical(110), gt)])
    assert (out["TP_count"], out["FP_count"], out["FN_count"]) == (3, 1, 1)
    assert out["F1_count"] == pytest.approx(0.75)
    assert out["F1"] == pytest.approx(0.8)


def test_counts_pair_lanes_one_to_one():
    # GT 1 (x 100) matches preds A and B; GT 2 (x 160 on its last 4 rows) matches A only (A: 19/20, B: 16/20).
    # Pairing GT 1 with A first would leave GT 2 unmatched; the largest matching pairs (1, B) and (2, A).
    gt = _vertical(100, 100)
    gt[1, 16:] = 160
    a = np.full(20, 100.0)
    a[17:] = 160
    pred = np.stack([a, np.full(20, 100.0)])
    assert tusimple_image_scores(pred, gt, ROWS, with_counts=True)[3:] == (2, 0, 0)
    # one prediction is the only match of two GT lanes (short ones, mostly outside: their -2 rows agree):
    # the official fp is 1 - 2 matched = -1; counted one-to-one, it is 1 TP and 1 FN
    short = _vertical(-2, -2)
    short[0, :2], short[1, :2] = 100, 112
    one = _vertical(-2)
    one[0, :2] = 106
    assert tusimple_image_scores(one, short, ROWS, with_counts=True) == (1.0, -1.0, 0.0, 1, 0, 1)


def test_counts_ignore_the_official_penalty_and_forgiveness():
    gt = _vertical(100, 300)
    five = _vertical(100, 300, 500, 700, 900)  # more than #gt + 2 predictions: officially (0, 0, 1)
    assert tusimple_image_scores(five, gt, ROWS, with_counts=True) == (0.0, 0.0, 1.0, 2, 3, 0)
    gt5 = _vertical(100, 300, 500, 700, 900)  # more than 4 GT lanes: officially one miss forgiven
    assert tusimple_image_scores(gt5[:4], gt5, ROWS, with_counts=True) == (1.0, 0.0, 0.0, 4, 0, 1)


def test_count_f1_formula():
    assert tusimple_count_f1(3, 1, 1) == pytest.approx(0.75)
    assert tusimple_count_f1(2, 0, 2) == pytest.approx(2 / 3)  # P 1, R 1/2
    assert tusimple_count_f1(0, 0, 0) == 0.0 and tusimple_count_f1(0, 5, 3) == 0.0
    assert "F1_count" not in tusimple_summary(1.0, 0.0, 0.0, 1)  # only with counts


def test_metric_f1_count_silent_and_ddp_merge_of_counts():
    """TuSimpleMetric from pixel lanes: a silent model's F1_count 0 (F1 2/3); two ranks' count states summed (as
    DDP's sync does) equal one pass."""
    lane = lambda x: np.stack([np.full(20, float(x)), ROWS], 1)  # noqa: E731
    gts = [[lane(100), lane(300)], [lane(100), lane(300)], [lane(500)]]
    preds = [[lane(105), lane(290), lane(900)], [lane(110)], [lane(505)]]  # TP 4, FP 1, FN 1
    silent = TuSimpleMetric()
    silent.update([[] for _ in gts], gts, ROWS)
    out = silent.compute()
    assert float(out["F1"]) == pytest.approx(2 / 3) and float(out["F1_count"]) == 0.0
    one = TuSimpleMetric()
    one.update(preds, gts, ROWS)
    ranks = [TuSimpleMetric(), TuSimpleMetric()]
    ranks[0].update(preds[:1], gts[:1], ROWS)
    ranks[1].update(preds[1:], gts[1:], ROWS)
    assert int(ranks[0].tp_count) == 2 and int(ranks[1].tp_count) == 2
    merged = ranks[0]
    for name, reduce_fx in ranks[0]._reductions.items():  # what sync() does with the gathered states
        setattr(merged, name, reduce_fx(torch.stack([getattr(r, name) for r in ranks])))
    whole, parts = one.compute(), merged.compute()
    assert (int(one.tp_count), int(one.fp_count), int(one.fn_count)) == (4, 1, 1)
    assert (int(merged.tp_count), int(merged.fp_count), int(merged.fn_count)) == (4, 1, 1)
    assert float(whole["F1_count"]) == pytest.approx(0.8)
    assert {k: float(v) for k, v in parts.items()} == {k: float(v) for k, v in whole.items()}
