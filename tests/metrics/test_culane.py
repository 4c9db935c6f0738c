"""CULane metric vs a slow, literal transcription of the official C++ evaluator."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch
from scipy.optimize import linear_sum_assignment

from lanevil_train.metrics import CULaneMetric, culane, culane_image_counts, culane_summary
from lanevil_train.metrics.culane import LaneCanvases, lane_polyline, official_km_match, spline_interp_times

W, H, LW = 1640, 590, 30


# ---------------------------------------------------------------- literal reference (slow, loops)
def ref_spline(pts: list[tuple[np.float32, np.float32]], times: int = 50) -> list[tuple[float, float]]:
    """spline.cpp splineInterpTimes + cal_fun, line by line (float32 subtractions as in C++)."""
    n = len(pts)
    X = [p[0] for p in pts]
    Y = [p[1] for p in pts]
    h = [math.sqrt(math.pow(float(X[i + 1] - X[i]), 2) + math.pow(float(Y[i + 1] - Y[i]), 2)) for i in range(n - 1)]
    A, B, C, Dx, Dy = [0.0] * (n - 2), [0.0] * (n - 2), [0.0] * (n - 2), [0.0] * (n - 2), [0.0] * (n - 2)
    for i in range(n - 2):
        A[i] = h[i]
        B[i] = 2 * (h[i] + h[i + 1])
        C[i] = h[i + 1]
        Dx[i] = 6 * (float(X[i + 2] - X[i + 1]) / h[i + 1] - float(X[i + 1] - X[i]) / h[i])
        Dy[i] = 6 * (float(Y[i + 2] - Y[i + 1]) / h[i + 1] - float(Y[i + 1] - Y[i]) / h[i])
    C[0] = C[0] / B[0]
    Dx[0] = Dx[0] / B[0]
    Dy[0] = Dy[0] / B[0]
    for i in range(1, n - 2):
        tmp = B[i] - A[i] * C[i - 1]
        C[i] = C[i] / tmp
        Dx[i] = (Dx[i] - A[i] * Dx[i - 1]) / tmp
        Dy[i] = (Dy[i] - A[i] * Dy[i - 1]) / tmp
    Mx, My = [0.0] * n, [0.0] * n
    Mx[n - 2] = Dx[n - 3]
    My[n - 2] = Dy[n - 3]
    for i in range(n - 4, -1, -1):
        Mx[i + 1] = Dx[i] - C[i] * Mx[i + 2]
        My[i + 1] = Dy[i] - C[i] * My[i + 2]
    Mx[0] = Mx[n - 1] = My[0] = My[n - 1] = 0.0
    res = []
    for i in range(n - 1):
        ax, ay = float(X[i]), float(Y[i])
        bx = float(X[i + 1] - X[i]) / h[i] - (2 * h[i] * Mx[i] + h[i] * Mx[i + 1]) / 6
        by = float(Y[i + 1] - Y[i]) / h[i] - (2 * h[i] * My[i] + h[i] * My[i + 1]) / 6
        cx, cy = Mx[i] / 2, My[i] / 2
        dx, dy = (Mx[i + 1] - Mx[i]) / (6 * h[i]), (My[i + 1] - My[i]) / (6 * h[i])
        delta = h[i] / times
        for k in range(times):
            t1 = delta * k
            x1 = ax + bx * t1 + cx * math.pow(t1, 2) + dx * math.pow(t1, 3)
            y1 = ay + by * t1 + cy * math.pow(t1, 2) + dy * math.pow(t1, 3)
            res.append((float(np.float32(x1)), float(np.float32(y1))))  # Point2f storage
    res.append((float(pts[-1][0]), float(pts[-1][1])))
    return res


def ref_mask(lane: np.ndarray) -> np.ndarray:
    """lane_compare.cpp: Point2f lane, spline if > 2 points, one cv::line per segment at cvRound points."""
    pts = [(np.float32(x), np.float32(y)) for x, y in lane]
    interp = [(float(x), float(y)) for x, y in pts] if len(pts) == 2 else ref_spline(pts)
    im = np.zeros((H, W), np.uint8)
    for n in range(len(interp) - 1):
        p1 = (round(interp[n][0]), round(interp[n][1]))  # Python round: half to even, like cvRound
        p2 = (round(interp[n + 1][0]), round(interp[n + 1][1]))
        cv2.line(im, p1, p2, 1, LW)
    return im


def ref_km(sim: list[list[float]]) -> tuple[list[int], list[int]]:
    """counter.cpp makeMatch + hungarianGraph.hpp, transcribed."""
    m, n = len(sim), len(sim[0])
    ex = m > n
    if ex:
        m, n = n, m
    mat = [[sim[j][i] if ex else sim[i][j] for j in range(n)] for i in range(m)]
    lm, rm, lw, rw = [-1] * m, [-1] * n, [-1e5] * m, [0.0] * n
    for i in range(m):
        for j in range(n):
            if lw[i] < mat[i][j]:
                lw[i] = mat[i][j]
    lu, ru = [False] * m, [False] * n

    def dfs(u):
        lu[u] = True
        for v in range(n):
            if not ru[v] and abs(lw[u] + rw[v] - mat[u][v]) < 1e-2:
                ru[v] = True
                if rm[v] == -1 or dfs(rm[v]):
                    rm[v] = u
                    lm[u] = v
                    return True
        return False

    def match():
        for u in range(m):
            while True:
                for i in range(m):
                    lu[i] = False
                for i in range(n):
                    ru[i] = False
                if dfs(u):
                    break
                d = 1e10
                for i in range(m):
                    if lu[i]:
                        for j in range(n):
                            if not ru[j]:
                                d = min(d, lw[i] + rw[j] - mat[i][j])
                if d == 1e10:
                    return
                for i in range(m):
                    if lu[i]:
                        lw[i] -= d
                for i in range(n):
                    if ru[i]:
                        rw[i] += d

    match()
    return (rm, lm) if ex else (lm, rm)


def ref_counts(pred: list, gt: list, thr: float = 0.5) -> tuple[int, int, int]:
    """counter.cpp count_im_pair with the literal pieces above."""
    if not gt:
        return 0, len(pred), 0
    if not pred:
        return 0, 0, len(gt)
    gm = [ref_mask(g) if len(g) >= 2 else None for g in gt]
    pm = [ref_mask(p) if len(p) >= 2 else None for p in pred]
    sim = []
    for a in gm:
        row = []
        for b in pm:
            if a is None or b is None:
                row.append(0.0)
                continue
            s1, s2, inter = float(a.sum()), float(b.sum()), float((a * b).sum())
            row.append(inter / (s1 + s2 - inter))
        sim.append(row)
    match, _ = ref_km(sim)
    tp = sum(1 for i in range(len(gt)) if match[i] >= 0 and sim[i][match[i]] > thr)
    return tp, len(pred) - tp, len(gt) - tp


# ---------------------------------------------------------------- random CULane-like cases
def random_lane(rng: np.random.Generator) -> np.ndarray:
    kind = rng.random()
    if kind < 0.15:  # 2-point lane, sometimes crossing the border
        return np.array([[rng.uniform(-200, W + 200), rng.uniform(400, 700)],
                         [rng.uniform(-100, W + 100), rng.uniform(150, 400)]])
    n = int(rng.integers(3, 9))
    y0, y1 = rng.uniform(560, 640), rng.uniform(200, 400)
    ys = np.sort(rng.uniform(y1, y0, n))[::-1]
    ys[0], ys[-1] = y0, y1
    x_bottom, x_top = rng.uniform(-300, W + 300), rng.uniform(600, 1000)
    s = (ys - y1) / (y0 - y1)
    xs = x_top + (x_bottom - x_top) * s + rng.uniform(-40, 40) * s * (1 - s) + rng.normal(0, 1.5, n)
    return np.stack([xs, ys], 1)


def perturb(lane: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    out = lane + np.array([rng.normal(0, 14), 0.0]) + rng.normal(0, 2, lane.shape)
    if rng.random() < 0.3 and len(lane) > 3:  # truncate the far end
        out = out[: int(rng.integers(2, len(lane)))]
    return out


def random_image(rng: np.random.Generator) -> tuple[list, list]:
    gt = [random_lane(rng) for _ in range(int(rng.integers(0, 5)))]
    pred = [perturb(g, rng) for g in gt if rng.random() < 0.85]
    pred += [random_lane(rng) for _ in range(int(rng.integers(0, 2)))]
    rng.shuffle(pred)
    return pred, gt


def test_counts_equal_literal_reference_on_many_random_images() -> None:
    rng = np.random.default_rng(0)
    total_fast, total_ref, diffs = np.zeros(3, int), np.zeros(3, int), []
    for k in range(220):
        pred, gt = random_image(rng)
        fast, ref = culane_image_counts(pred, gt), ref_counts(pred, gt)
        if fast != ref:
            diffs.append((k, fast, ref))
        total_fast += fast
        total_ref += ref
    assert not diffs
    assert tuple(total_fast) == tuple(total_ref)
    tp, fp, fn = total_ref
    assert tp > 100 and fp > 30 and fn > 30  # the cases really exercise hits and misses


def test_drawn_masks_equal_per_segment_cv_line() -> None:
    """polylines on a reused plane == the official one-cv::line-per-segment mask, incl. lanes leaving the canvas."""
    rng = np.random.default_rng(1)
    canvases = LaneCanvases(H, W)
    for i in range(60):
        lane = random_lane(rng)
        ref = ref_mask(lane).astype(bool)
        m = canvases.draw(i % 3, lane_polyline(lane.astype(np.float32)), LW)
        assert np.array_equal(m.pixels(), ref)
        assert np.array_equal(m.plane.astype(bool), ref)  # nothing drawn outside the box
        assert m.area == int(ref.sum())
        canvases.clear([m])
        assert not any(plane.any() for plane in canvases.planes)
    for _ in range(6):  # dense CULane-style lanes: a point every 10 rows, many duplicate rounded samples
        ys = np.arange(589.0, rng.uniform(250, 350), -10.0)
        xs = rng.uniform(100, 1500) + rng.uniform(-1.5, 1.5) * (589 - ys) + rng.normal(0, 0.7, len(ys))
        lane = np.stack([xs, ys], 1)
        m = canvases.draw(0, lane_polyline(lane.astype(np.float32)), LW)
        assert np.array_equal(m.pixels(), ref_mask(lane).astype(bool))
        canvases.clear([m])


def test_planes_are_clean_after_a_bad_lane() -> None:
    """A lane that raises mid-image must not leave earlier lanes on the reused planes."""
    g = np.array([[100.0, 589.0], [200.0, 450.0], [260.0, 300.0]])
    with pytest.raises(ValueError, match="pred lane 1"):
        culane_image_counts([g, np.zeros((3, 3))], [g])
    assert not any(plane.any() for plane in culane.thread_canvases(H, W).planes)
    assert culane_image_counts([g + [400, 0]], [g]) == (0, 1, 1)


def test_spline_matches_reference_and_interpolates() -> None:
    lane = np.array([[100.3, 589.0], [180.7, 500.2], [300.1, 420.9], [450.5, 300.0]], np.float32)
    fast = spline_interp_times(lane)
    ref = np.array(ref_spline([(x, y) for x, y in lane]), np.float32)
    assert fast.shape == (3 * 50 + 1, 2)
    assert np.array_equal(fast, ref)
    assert np.array_equal(fast[::50], lane)  # passes through every knot
    # natural spline of collinear points is the straight line itself
    line = np.array([[0, 0], [10, 20], [30, 60]], np.float32)
    s = spline_interp_times(line)
    assert np.allclose(s[:, 1], 2 * s[:, 0], atol=1e-4)


def test_repeated_point_gives_nan_samples_like_the_cpp() -> None:
    lane = np.array([[100.0, 589.0], [200.0, 450.0], [200.0, 450.0], [260.0, 300.0]], np.float32)
    s = spline_interp_times(lane)
    assert s.shape == (151, 2) and np.isnan(s[:-1]).all() and s[-1].tolist() == [260.0, 300.0]
    with pytest.raises(ZeroDivisionError):  # the literal transcription divides 0/0 at the same place
        ref_spline([(x, y) for x, y in lane])


def test_km_tolerance_differs_from_exact_assignment() -> None:
    """The official 1e-2-tolerant KM picks a near-optimal matching scipy would not: TP 1 instead of 2."""
    sim = [[0.9, 0.9], [0.499, 0.505]]
    assert official_km_match(sim) == ref_km(sim) == ([1, 0], [1, 0])
    r, c = linear_sum_assignment(-np.array(sim))
    assert list(c) == [0, 1]
    rng = np.random.default_rng(2)
    for _ in range(300):
        m, n = int(rng.integers(1, 6)), int(rng.integers(1, 6))
        s = np.round(rng.random((m, n)), 2 if rng.random() < 0.5 else 6).tolist()
        assert official_km_match(s) == ref_km(s)


def test_iou_threshold_is_strict_and_two_point_lanes() -> None:
    gt = [np.array([[800.0, 580.0], [800.0, 300.0]])]
    ref_g = ref_mask(gt[0]).astype(bool)
    # find a horizontal shift with IoU just above and just below 0.5
    ious = {}
    for dx in range(5, 30):
        p = ref_mask(gt[0] + [dx, 0]).astype(bool)
        ious[dx] = (ref_g & p).sum() / (ref_g | p).sum()
    above = max(d for d, v in ious.items() if v > 0.5)
    below = min(d for d, v in ious.items() if v <= 0.5)
    assert below == above + 1
    assert culane_image_counts([gt[0] + [above, 0]], gt) == (1, 0, 0)
    assert culane_image_counts([gt[0] + [below, 0]], gt) == (0, 1, 1)
    # threshold exactly at the IoU value: strict '>' rejects it
    p = gt[0] + [above, 0]
    assert culane_image_counts([p], gt, iou_threshold=float(ious[above])) == (0, 1, 1)
    assert culane_image_counts([p], gt, iou_threshold=float(ious[above]) - 1e-9) == (1, 0, 0)


def test_edge_cases() -> None:
    g = np.array([[100.0, 589.0], [200.0, 450.0], [260.0, 300.0]])
    assert culane_image_counts([], [g]) == (0, 0, 1)
    assert culane_image_counts([g], []) == (0, 1, 0)
    assert culane_image_counts([g, g], [g]) == (1, 1, 0)
    # a 1-point lane has similarity 0 but still counts as a lane
    assert culane_image_counts([np.array([[100.0, 589.0]])], [g]) == (0, 1, 1)
    # a lane fully outside the canvas never matches
    assert culane_image_counts([g + [3000, 0]], [g]) == (0, 1, 1)
    with pytest.raises(ValueError, match="pred lane 0"):
        culane_image_counts([np.zeros((3, 3))], [g])


def test_summary_and_metric_equal_function() -> None:
    assert culane_summary(8, 2, 2) == {"TP": 8, "FP": 2, "FN": 2, "Precision": 0.8, "Recall": 0.8,
                                        "F1": pytest.approx(0.8)}
    assert culane_summary(0, 0, 0)["F1"] == 0.0
    rng = np.random.default_rng(3)
    imgs = [random_image(rng) for _ in range(30)]
    metric = CULaneMetric()
    metric.update([p for p, _ in imgs[:12]], [g for _, g in imgs[:12]])
    metric.update([p for p, _ in imgs[12:]], [g for _, g in imgs[12:]])
    counts = np.sum([culane_image_counts(p, g) for p, g in imgs], axis=0)
    out = metric.compute()
    assert {k: out[k] for k in culane_summary(0, 0, 0)} == culane_summary(*counts) and out["images"] == 30
    at75 = np.sum([culane_image_counts(p, g, iou_threshold=0.75) for p, g in imgs], axis=0)
    assert out["F1@50"] == culane_summary(*counts)["F1"] and out["F1@75"] == culane_summary(*at75)["F1"]
    assert isinstance(metric.tp, torch.Tensor) and metric.tp.dtype == torch.long
