"""CULane F1, reproducing the official C++ evaluator (``evaluate`` of the CULane/SCNN release) exactly.

Procedure of the official tool (evaluate.cpp, counter.cpp, lane_compare.cpp, spline.cpp, hungarianGraph.hpp):

* Lanes are read as ``cv::Point2f`` (float32). A lane with exactly 2 points is drawn as its segment; a lane
  with more points is replaced by ``Spline::splineInterpTimes(lane, 50)``: a natural cubic spline (second
  derivative 0 at both ends, solved by the Thomas algorithm) in x(t), y(t) with t the chord length of each
  segment, 50 samples per segment (t = k*h/50, k = 0..49), then the last input point. Samples are stored as
  float32 and converted to integer pixels by OpenCV (``cvRound``: round half to even).
* Each lane is drawn with ``cv::line`` segment by segment, thickness ``lane_width`` (30), LINE_8, on a
  ``height x width`` (590 x 1640) canvas; IoU = |A & B| / |A | B| of the masks (a lane with < 2 points has
  similarity 0).
* Matching is the Kuhn-Munkres routine of hungarianGraph.hpp: it maximises the IoU sum but treats an edge as
  "tight" when |l_u + r_v - w| < 1e-2, so on near-ties (within 0.01) it can return a matching that an exact
  solver (scipy ``linear_sum_assignment``) would not, and the TP count can differ. It is ported here as is,
  including its choice of the smaller side as the left side.
* Repeated consecutive points in a > 2-point lane give a zero chord, hence NaN spline samples, which
  ``cvRound`` turns into INT_MIN on x86; this is reproduced (the lane then draws a stray long line), not fixed.
* A matched pair is a TP when IoU > threshold (strict); FP = #pred - TP, FN = #gt - TP, summed over images.

Several thresholds from one pass (cfzd/Ultra-Fast-Lane-Detection 353df10, ``evaluation/culane/``): the matching
never sees the threshold. ``counter.cpp:77-90`` fills the raw-IoU matrix and calls ``makeMatch``; only afterwards,
``counter.cpp:97``, is a matched pair a TP when ``similarity > sim_threshold``, the only use of the threshold
(``counter.hpp:22,39``). So ``culane_matched_ious`` computes the masks, IoUs and matching once per image and
``culane_image_counts_multi`` counts the TP at every threshold from them, each count equal to a separate
``evaluate -t <threshold>`` run (tests/metrics/test_culane_categories.py; benchmarks/RESULTS.md, "CULane as
leaderboards report it"). mF1 is CLRNet's (Turoad/CLRNet 7269e9d ``clrnet/utils/culane_metric.py:166-203`` with
``np.linspace(0.5, 0.95, 10)`` from ``clrnet/datasets/culane.py:140``): the mean of the ten F1 values at
0.50, 0.55, ..., 0.95, each from the counts summed over the list. ``MF1_THRESHOLDS`` are the decimal literals,
which ``evaluate -t 0.90`` reads with atof; linspace's ninth value is 0.8999999999999999, so a pair with IoU
exactly 0.9 would be a TP at "0.9" in CLRNet's Python and not in the C++ (and not here).

Categories (``culane_files.CATEGORIES``): the official scripts run the evaluator once per list of
``list/test_split/`` (``run-full.sh:10-36``, ``evaluation/eval_wrapper.py:185-237``) and sum the nine lists'
counts for the total (``calTotal.m:11-23``). Cross images have no GT lanes, so TP = FN = 0 and FP = #pred
(``counter.cpp:65-68``); the evaluator prints recall -1 (``counter.cpp:23-27``) and F 0, and leaderboards give
cross's FP count. Here one pass over the scored list gives every image's TP at every threshold, summed per list.

Why the widely copied Python port (``culane_metric`` with scipy ``splprep``) gives different counts:
it fits FITPACK's interpolating B-spline (``splprep(s=0)``: its own end conditions, parameter =
normalised cumulative chord length) instead of the natural cubic spline, samples 5 points per segment instead of 50 (a
coarser polyline), truncates coordinates to int (``astype(np.int32)``) instead of rounding, and matches with the exact
``linear_sum_assignment`` instead of the 1e-2-tolerant Kuhn-Munkres. Each of these moves masks or matches by
a pixel or a near-tie, which flips IoU > 0.5 decisions on some lanes (measured here: 1 of 300 synthetic
CULane-like images got different counts).

Here, a lane's polyline is drawn once per image, not once per pair as officially, with ``cv2.polylines`` (in
OpenCV this is the same ``ThickLine`` calls as per-segment ``cv::line``, with the shared end caps drawn once),
on its own full-size plane so clipping is the official one; IoUs are counted on the overlap of the lanes'
bounding boxes only, and pairs whose boxes do not overlap cost nothing. Reading ``.lines.txt`` trees is
``culane_files.py``; the torchmetrics wrapper is ``wrappers.CULaneMetric``.
"""

from __future__ import annotations

import math
import threading
from typing import Mapping, Sequence

import cv2
import numpy as np

SAMPLES_PER_SEGMENT = 50
_TIGHT_EPS = 1e-2  # hungarianGraph.hpp equality tolerance
_INT_MIN = np.iinfo(np.int32).min
# mF1's IoU thresholds 0.50:0.05:0.95 as decimal literals (what `evaluate -t 0.90` reads with atof; CLRNet's
# np.linspace(0.5, 0.95, 10) gives 0.8999999999999999 for the ninth, see the module docstring)
MF1_THRESHOLDS = (0.5, 0.55, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95)


def lane_points(lane: object, name: str) -> np.ndarray:
    """Lane as an (N, 2) float64 array of (x, y) points (an empty lane as (0, 2)); raises naming ``name``
    otherwise. Shared with metrics/llamas.py."""
    arr = np.asarray(lane, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, 2))
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name}: expected an (N, 2) array of (x, y) points, got shape {arr.shape}")
    return arr


def _as_f32_lane(lane: object, name: str) -> np.ndarray:
    """Lane as an (N, 2) float32 array (the official ``Point2f``); raises naming ``name`` otherwise."""
    return lane_points(lane, name).astype(np.float32)


def spline_interp_times(lane: np.ndarray, times: int = SAMPLES_PER_SEGMENT) -> np.ndarray:
    """Official ``Spline::splineInterpTimes`` for > 2 points: natural cubic spline by chord length, float32 out."""
    p = np.asarray(lane, dtype=np.float32)
    n = len(p)
    if n <= 2:
        raise ValueError(f"spline_interp_times needs > 2 points, got {n}")
    out = np.empty(((n - 1) * times + 1, 2), np.float32)
    out[-1] = p[-1]
    dx = (p[1:, 0] - p[:-1, 0]).astype(np.float64)  # float32 differences, as C++ float - float
    dy = (p[1:, 1] - p[:-1, 1]).astype(np.float64)
    h = np.sqrt(dx * dx + dy * dy)  # pow(v, 2) is exactly v * v
    if not np.all(h > 0):
        # A zero chord makes the C++ divide 0/0: the NaN spreads through the tridiagonal solve to every
        # sample; only the appended last point survives.
        out[:-1] = np.nan
        return out
    sx, sy = dx / h, dy / h
    hl, sxl, syl = h.tolist(), sx.tolist(), sy.tolist()
    m = n - 2
    A, B, C = hl[:m], [2 * (hl[i] + hl[i + 1]) for i in range(m)], hl[1 : m + 1]
    Dx = [6 * (sxl[i + 1] - sxl[i]) for i in range(m)]
    Dy = [6 * (syl[i + 1] - syl[i]) for i in range(m)]
    C[0], Dx[0], Dy[0] = C[0] / B[0], Dx[0] / B[0], Dy[0] / B[0]
    for i in range(1, m):  # Thomas algorithm, same operation order as cal_fun
        tmp = B[i] - A[i] * C[i - 1]
        C[i] = C[i] / tmp
        Dx[i] = (Dx[i] - A[i] * Dx[i - 1]) / tmp
        Dy[i] = (Dy[i] - A[i] * Dy[i - 1]) / tmp
    Mx, My = [0.0] * n, [0.0] * n
    Mx[n - 2], My[n - 2] = Dx[m - 1], Dy[m - 1]
    for i in range(m - 2, -1, -1):
        Mx[i + 1] = Dx[i] - C[i] * Mx[i + 2]
        My[i + 1] = Dy[i] - C[i] * My[i + 2]
    Mx[0] = Mx[n - 1] = My[0] = My[n - 1] = 0.0
    Mxa, Mya = np.array(Mx), np.array(My)
    bx = sx - (2 * h * Mxa[:-1] + h * Mxa[1:]) / 6
    by = sy - (2 * h * Mya[:-1] + h * Mya[1:]) / 6
    cx, cy = Mxa[:-1] / 2, Mya[:-1] / 2
    ex, ey = (Mxa[1:] - Mxa[:-1]) / (6 * h), (Mya[1:] - Mya[:-1]) / (6 * h)
    t = (h / times)[:, None] * np.arange(times, dtype=np.float64)[None, :]
    t2, t3 = t * t, np.power(t, 3.0)  # pow(t, 2) == t * t exactly; pow(t, 3) from libm like the C++
    ax, ay = p[:-1, 0].astype(np.float64)[:, None], p[:-1, 1].astype(np.float64)[:, None]
    out[:-1, 0] = (ax + bx[:, None] * t + cx[:, None] * t2 + ex[:, None] * t3).ravel()
    out[:-1, 1] = (ay + by[:, None] * t + cy[:, None] * t2 + ey[:, None] * t3).ravel()
    return out


def cv_round(points: np.ndarray) -> np.ndarray:
    """OpenCV's Point2f -> Point conversion (cvRound: half to even; NaN/inf/overflow -> INT_MIN on x86)."""
    r = np.rint(np.asarray(points, dtype=np.float32).astype(np.float64))
    bad = ~np.isfinite(r) | (r < _INT_MIN) | (r > np.iinfo(np.int32).max)
    r[bad] = _INT_MIN
    return r.astype(np.int32)


def lane_polyline(lane: np.ndarray) -> np.ndarray | None:
    """Integer drawing polyline of a lane as the official tool builds it (None when it has < 2 points)."""
    if len(lane) < 2:
        return None
    pts = cv_round(lane if len(lane) == 2 else spline_interp_times(lane))
    # A repeated point adds a zero-length segment whose pixels lie inside the round cap already drawn
    # there, so dropping consecutive duplicates leaves the mask unchanged (checked against cv::line in tests).
    xy = pts.view(np.int64).ravel()  # one 64-bit word per (x, y) int32 pair: a single comparison per point
    keep = np.empty(len(xy), bool)
    keep[0] = True
    np.not_equal(xy[1:], xy[:-1], out=keep[1:])
    return pts[keep]


class _Mask:
    """A drawn lane: the plane it is drawn on, its bounding box there, and its pixel count."""

    __slots__ = ("plane", "x0", "y0", "x1", "y1", "area")

    def __init__(self, plane: np.ndarray, x0: int, y0: int, x1: int, y1: int) -> None:
        self.plane, self.x0, self.y0, self.x1, self.y1 = plane, x0, y0, x1, y1
        self.area = int(np.count_nonzero(plane[y0:y1, x0:x1])) if x0 < x1 and y0 < y1 else 0

    def pixels(self) -> np.ndarray:
        """The mask as a full (height, width) bool array (for tests and debugging)."""
        out = np.zeros(self.plane.shape, bool)
        out[self.y0 : self.y1, self.x0 : self.x1] = self.plane[self.y0 : self.y1, self.x0 : self.x1]
        return out


class LaneCanvases:
    """Zeroed full-size uint8 planes, one per lane of an image, reused from image to image.

    Each lane is drawn on its own (height, width) plane, so OpenCV clips exactly as on the official canvas,
    and only its bounding box is read and, in ``clear``, zeroed again. Reusing the planes instead of allocating
    a canvas and a crop per lane saves the page faults of fresh memory (a fifth of the CPU time).
    """

    KEEP = 16  # planes kept between images; an image with more lanes allocates the extra ones

    def __init__(self, height: int, width: int) -> None:
        self.shape = (height, width)
        self.planes: list[np.ndarray] = []
        self.scratch = np.empty(self.shape, np.uint8)

    def draw(self, k: int, poly: np.ndarray, lane_width: int) -> _Mask:
        """Draw the integer polyline ``poly`` (thickness ``lane_width``) on plane ``k`` and return its mask."""
        while len(self.planes) <= k:
            self.planes.append(np.zeros(self.shape, np.uint8))
        plane, (hgt, wid), pad = self.planes[k], self.shape, lane_width + 2
        x0, y0 = max(int(poly[:, 0].min()) - pad, 0), max(int(poly[:, 1].min()) - pad, 0)
        x1, y1 = min(int(poly[:, 0].max()) + pad + 1, wid), min(int(poly[:, 1].max()) + pad + 1, hgt)
        if x0 < x1 and y0 < y1:  # else entirely off the canvas: nothing can be drawn
            cv2.polylines(plane, [poly.reshape(-1, 1, 2)], False, 1, lane_width)
        return _Mask(plane, x0, y0, x1, y1)

    def iou(self, a: _Mask, b: _Mask) -> float:
        """IoU of two drawn lanes (NaN when both are empty, like the official 0/0)."""
        inter = 0
        ox0, oy0, ox1, oy1 = max(a.x0, b.x0), max(a.y0, b.y0), min(a.x1, b.x1), min(a.y1, b.y1)
        if ox0 < ox1 and oy0 < oy1 and a.area and b.area:  # boxes apart: no common pixel
            both = np.bitwise_and(a.plane[oy0:oy1, ox0:ox1], b.plane[oy0:oy1, ox0:ox1],
                                  out=self.scratch[: oy1 - oy0, : ox1 - ox0])
            inter = int(np.count_nonzero(both))
        union = a.area + b.area - inter
        return inter / union if union else math.nan

    def clear(self, masks: Sequence[_Mask]) -> None:
        """Zero what ``masks`` drew (every drawn pixel lies in its box) and drop planes beyond ``KEEP``."""
        for m in masks:
            m.plane[m.y0 : m.y1, m.x0 : m.x1] = 0
        del self.planes[self.KEEP :]


_local = threading.local()


def thread_canvases(height: int, width: int) -> LaneCanvases:
    """This thread's LaneCanvases for the canvas size (threads never share planes)."""
    c = getattr(_local, "canvases", None)
    if c is None or c.shape != (height, width):
        c = _local.canvases = LaneCanvases(height, width)
    return c


def official_km_match(sim: Sequence[Sequence[float]]) -> tuple[list[int], list[int]]:
    """Port of counter.cpp ``makeMatch`` + hungarianGraph.hpp: (match of each row, match of each column)."""
    m, n = len(sim), len(sim[0])
    swap = m > n
    mat = [[sim[j][i] for j in range(m)] for i in range(n)] if swap else [list(r) for r in sim]
    L, R = len(mat), len(mat[0])
    lmatch, rmatch = [-1] * L, [-1] * R
    rw = [0.0] * R
    lw = []
    for i in range(L):
        w = -1e5
        for j in range(R):
            if w < mat[i][j]:
                w = mat[i][j]
        lw.append(w)

    def dfs(u: int, lused: list[bool], rused: list[bool]) -> bool:
        lused[u] = True
        for v in range(R):
            if not rused[v] and abs(lw[u] + rw[v] - mat[u][v]) < _TIGHT_EPS:
                rused[v] = True
                if rmatch[v] == -1 or dfs(rmatch[v], lused, rused):
                    rmatch[v], lmatch[u] = u, v
                    return True
        return False

    done = False
    for u in range(L):
        while not done:
            lused, rused = [False] * L, [False] * R
            if dfs(u, lused, rused):
                break
            d = 1e10
            for i in range(L):
                if lused[i]:
                    for j in range(R):
                        if not rused[j]:
                            c = lw[i] + rw[j] - mat[i][j]
                            if c < d:  # std::min(d, c) keeps d when c is NaN
                                d = c
            if d == 1e10:
                done = True  # the C++ returns from match() here
                break
            for i in range(L):
                if lused[i]:
                    lw[i] -= d
            for j in range(R):
                if rused[j]:
                    rw[j] += d
        if done:
            break
    return (rmatch, lmatch) if swap else (lmatch, rmatch)


def culane_matched_ious(
    pred_lanes: Sequence[object],
    gt_lanes: Sequence[object],
    width: int = 1640,
    height: int = 590,
    lane_width: int = 30,
) -> list[float]:
    """IoU of every (GT, prediction) pair the official matching pairs in one image (NaN for two empty masks).

    The matching maximises the summed raw IoU and never sees the threshold (counter.cpp makeMatch), so these IoUs
    give the TP count at every threshold: TP(t) = the number of them > t."""
    if not gt_lanes or not pred_lanes:
        return []
    if width < 1 or height < 1 or lane_width < 1:
        raise ValueError(f"width, height, lane_width must be positive, got {width}, {height}, {lane_width}")
    canvases = thread_canvases(height, width)
    drawn: list[_Mask] = []
    try:  # the planes are reused: whatever happens, zero what was drawn
        masks: list[list[_Mask | None]] = []
        for kind, lanes in (("gt", gt_lanes), ("pred", pred_lanes)):
            row: list[_Mask | None] = []
            for k, lane in enumerate(lanes):
                poly = lane_polyline(_as_f32_lane(lane, f"{kind} lane {k}"))
                if poly is None:  # < 2 points: similarity 0 to everything, as officially
                    row.append(None)
                    continue
                drawn.append(canvases.draw(len(drawn), poly, lane_width))
                row.append(drawn[-1])
            masks.append(row)
        gm, pm = masks
        sim = [[0.0 if (g is None or p is None) else canvases.iou(g, p) for p in pm] for g in gm]
    finally:
        canvases.clear(drawn)
    gt_match, _ = official_km_match(sim)
    return [sim[i][j] for i, j in enumerate(gt_match) if j >= 0]


def culane_image_counts_multi(
    pred_lanes: Sequence[object],
    gt_lanes: Sequence[object],
    width: int = 1640,
    height: int = 590,
    lane_width: int = 30,
    iou_thresholds: Sequence[float] = MF1_THRESHOLDS,
) -> list[tuple[int, int, int]]:
    """(TP, FP, FN) of one image at each of ``iou_thresholds``, from one IoU matrix and one matching: each equal
    to ``culane_image_counts`` at that threshold (a TP is a matched pair with IoU > threshold, strict)."""
    ious = culane_matched_ious(pred_lanes, gt_lanes, width, height, lane_width)
    out = []
    for threshold in iou_thresholds:
        tp = sum(1 for iou in ious if iou > threshold)  # NaN > t is False, as in the C++
        out.append((tp, len(pred_lanes) - tp, len(gt_lanes) - tp))
    return out


def culane_image_counts(
    pred_lanes: Sequence[object],
    gt_lanes: Sequence[object],
    width: int = 1640,
    height: int = 590,
    lane_width: int = 30,
    iou_threshold: float = 0.5,
) -> tuple[int, int, int]:
    """(TP, FP, FN) of one image exactly as the official CULane evaluator counts them."""
    return culane_image_counts_multi(pred_lanes, gt_lanes, width, height, lane_width, (iou_threshold,))[0]


def culane_summary(tp: int, fp: int, fn: int) -> dict:
    """Precision, recall and F1 from summed counts (0 where a denominator is 0; the C++ prints -1/nan)."""
    precision = tp / (tp + fp) if tp + fp else 0.0
    recall = tp / (tp + fn) if tp + fn else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {"TP": int(tp), "FP": int(fp), "FN": int(fn), "Precision": precision, "Recall": recall, "F1": f1}


def culane_leaderboard_scores(counts: Mapping[float, Sequence[int]]) -> dict:
    """F1@50, F1@75 and mF1 (fractions) from summed (TP, FP, FN) per IoU threshold; ``counts`` must hold every
    threshold of MF1_THRESHOLDS. mF1 is the mean of the ten F1 values at 0.50, 0.55, ..., 0.95 (CLRNet's), each
    F1 from the counts summed over all images at that threshold."""
    missing = [t for t in MF1_THRESHOLDS if t not in counts]
    if missing:
        raise ValueError(f"counts lack the IoU thresholds {missing}; mF1 needs {list(MF1_THRESHOLDS)}")
    f1 = {t: culane_summary(*counts[t])["F1"] for t in MF1_THRESHOLDS}
    return {"F1@50": f1[0.5], "F1@75": f1[0.75], "mF1": sum(f1.values()) / len(f1)}


def culane_sweep_summary(counts: Mapping[float, Sequence[int]]) -> dict:
    """TP, FP, FN, Precision, Recall at IoU 0.5 and F1@50, F1@75, mF1 (culane_leaderboard_scores)."""
    at50 = culane_summary(*counts[0.5])
    return {**{k: at50[k] for k in ("TP", "FP", "FN", "Precision", "Recall")}, **culane_leaderboard_scores(counts)}
