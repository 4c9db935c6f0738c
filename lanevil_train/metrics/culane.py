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

Why the widely copied Python port (``culane_metric`` with scipy ``splprep``) gives different counts:
it fits FITPACK's interpolating B-spline (``splprep(s=0)``: its own end conditions, parameter =
normalised cumulative chord length) instead of the natural cubic spline, samples 5 points per segment instead of 50 (a coarser polyline),
truncates coordinates to int (``astype(np.int32)``) instead of rounding, and matches with the exact
``linear_sum_assignment`` instead of the 1e-2-tolerant Kuhn-Munkres. Each of these moves masks or matches by
a pixel or a near-tie, which flips IoU > 0.5 decisions on some lanes (measured here: 1 of 300 synthetic
CULane-like images got different counts).

Here, a lane's polyline is drawn once with ``cv2.polylines`` (in OpenCV this is the same ``ThickLine`` calls
as per-segment ``cv::line``, with the shared end caps drawn once), on the full canvas so clipping is the
official one, and IoUs are computed on the overlap of the lanes' bounding boxes.
"""

from __future__ import annotations

import math
import os
from typing import Sequence

import cv2
import numpy as np
import torch
from torchmetrics import Metric

SAMPLES_PER_SEGMENT = 50
_TIGHT_EPS = 1e-2  # hungarianGraph.hpp equality tolerance
_INT_MIN = np.iinfo(np.int32).min


def _as_f32_lane(lane: object, name: str) -> np.ndarray:
    """Lane as an (N, 2) float32 array (the official ``Point2f``); raises naming ``name`` otherwise."""
    arr = np.asarray(lane, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, 2), np.float32)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name}: expected an (N, 2) array of (x, y) points, got shape {arr.shape}")
    return arr.astype(np.float32)


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
    keep = np.ones(len(pts), bool)
    keep[1:] = np.any(pts[1:] != pts[:-1], axis=1)
    return pts[keep]


class _Mask:
    """A drawn lane: a boolean crop of the canvas, its top-left corner and its pixel count."""

    __slots__ = ("x0", "y0", "crop", "area")

    def __init__(self, x0: int, y0: int, crop: np.ndarray) -> None:
        self.x0, self.y0, self.crop = x0, y0, crop
        self.area = int(np.count_nonzero(crop))


def _draw(canvas: np.ndarray, poly: np.ndarray, lane_width: int) -> _Mask:
    """Draw ``poly`` on the (all-zero) canvas, cut out its bounding box, and clear the canvas again."""
    hgt, wid = canvas.shape
    pad = lane_width + 2
    x0 = max(int(poly[:, 0].min()) - pad, 0)
    y0 = max(int(poly[:, 1].min()) - pad, 0)
    x1 = min(int(poly[:, 0].max()) + pad + 1, wid)
    y1 = min(int(poly[:, 1].max()) + pad + 1, hgt)
    if x0 >= x1 or y0 >= y1:  # entirely off the canvas: nothing can be drawn
        return _Mask(0, 0, np.zeros((0, 0), bool))
    cv2.polylines(canvas, [poly.reshape(-1, 1, 2)], False, 1, lane_width)
    crop = canvas[y0:y1, x0:x1].astype(bool)
    canvas[y0:y1, x0:x1] = 0
    return _Mask(x0, y0, crop)


def _iou(a: _Mask, b: _Mask) -> float:
    """IoU of two drawn lanes (NaN when both are empty, like the official 0/0)."""
    union_base = a.area + b.area
    inter = 0
    ox0, oy0 = max(a.x0, b.x0), max(a.y0, b.y0)
    ox1 = min(a.x0 + a.crop.shape[1], b.x0 + b.crop.shape[1])
    oy1 = min(a.y0 + a.crop.shape[0], b.y0 + b.crop.shape[0])
    if ox0 < ox1 and oy0 < oy1 and a.area and b.area:
        ca = a.crop[oy0 - a.y0 : oy1 - a.y0, ox0 - a.x0 : ox1 - a.x0]
        cb = b.crop[oy0 - b.y0 : oy1 - b.y0, ox0 - b.x0 : ox1 - b.x0]
        inter = int(np.count_nonzero(ca & cb))
    union = union_base - inter
    return inter / union if union else math.nan


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


def culane_image_counts(
    pred_lanes: Sequence[object],
    gt_lanes: Sequence[object],
    width: int = 1640,
    height: int = 590,
    lane_width: int = 30,
    iou_threshold: float = 0.5,
) -> tuple[int, int, int]:
    """(TP, FP, FN) of one image exactly as the official CULane evaluator counts them."""
    if not gt_lanes:
        return 0, len(pred_lanes), 0
    if not pred_lanes:
        return 0, 0, len(gt_lanes)
    if width < 1 or height < 1 or lane_width < 1:
        raise ValueError(f"width, height, lane_width must be positive, got {width}, {height}, {lane_width}")
    canvas = np.zeros((height, width), np.uint8)
    masks: list[list[_Mask | None]] = []
    for kind, lanes in (("gt", gt_lanes), ("pred", pred_lanes)):
        row = []
        for k, lane in enumerate(lanes):
            poly = lane_polyline(_as_f32_lane(lane, f"{kind} lane {k}"))
            row.append(None if poly is None else _draw(canvas, poly, lane_width))
        masks.append(row)
    gm, pm = masks
    sim = [[0.0 if (g is None or p is None) else _iou(g, p) for p in pm] for g in gm]
    gt_match, _ = official_km_match(sim)
    tp = sum(1 for i, j in enumerate(gt_match) if j >= 0 and sim[i][j] > iou_threshold)
    return tp, len(pred_lanes) - tp, len(gt_lanes) - tp


def culane_summary(tp: int, fp: int, fn: int) -> dict:
    """Precision, recall and F1 from summed counts (0 where a denominator is 0; the C++ prints -1/nan)."""
    precision = tp / (tp + fp) if tp + fp else 0.0
    recall = tp / (tp + fn) if tp + fn else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {"TP": int(tp), "FP": int(fp), "FN": int(fn), "Precision": precision, "Recall": recall, "F1": f1}


def read_lines_file(path: str) -> list[np.ndarray]:
    """Lanes of a CULane ``.lines.txt`` like the official reader: one lane per line of "x y x y ..." pairs.

    A missing file means no lanes (as in evaluate.cpp); an odd trailing number is ignored like ``ss>>x>>y``;
    a non-numeric token raises ValueError naming file and line. Blank lines are lanes with 0 points (the C++
    counts them too).
    """
    if not os.path.exists(path):
        return []
    lanes = []
    with open(path) as f:
        for lineno, line in enumerate(f, 1):
            tokens = line.split()
            try:
                vals = [float(t) for t in tokens]
            except ValueError as e:
                raise ValueError(f"{path}:{lineno}: expected numbers 'x y x y ...', got {line.strip()!r}") from e
            vals = vals[: len(vals) // 2 * 2]
            lanes.append(np.asarray(vals, np.float64).reshape(-1, 2))
    return lanes


def evaluate_culane_dirs(
    pred_dir: str,
    gt_dir: str,
    list_file: str,
    width: int = 1640,
    height: int = 590,
    lane_width: int = 30,
    iou_threshold: float = 0.5,
) -> dict:
    """Official file-level evaluation: for each image path in ``list_file``, ``<dir>/<path sans ext>.lines.txt``."""
    if not os.path.isfile(list_file):
        raise FileNotFoundError(f"list file {list_file} does not exist")
    tp = fp = fn = 0
    with open(list_file) as f:
        names = [ln.rstrip("\r\n") for ln in f]
    for name in names:
        if not name.strip():
            continue
        stem = name.strip().lstrip("/")
        stem = stem[: stem.rfind(".")] if "." in os.path.basename(stem) else stem
        rel = stem + ".lines.txt"
        counts = culane_image_counts(
            read_lines_file(os.path.join(pred_dir, rel)), read_lines_file(os.path.join(gt_dir, rel)),
            width, height, lane_width, iou_threshold,
        )
        tp, fp, fn = tp + counts[0], fp + counts[1], fn + counts[2]
    return culane_summary(tp, fp, fn)


class CULaneMetric(Metric):
    """Streaming CULane F1: TP/FP/FN summed over images (sum-reduced across processes)."""

    full_state_update = False
    higher_is_better = True

    def __init__(self, width: int = 1640, height: int = 590, lane_width: int = 30, iou_threshold: float = 0.5,
                 **kwargs: object) -> None:
        super().__init__(**kwargs)
        self.width, self.height, self.lane_width, self.iou_threshold = width, height, lane_width, iou_threshold
        for name in ("tp", "fp", "fn"):
            self.add_state(name, default=torch.tensor(0, dtype=torch.long), dist_reduce_fx="sum")

    def update(self, preds: Sequence[Sequence[object]], targets: Sequence[Sequence[object]]) -> None:
        """Add the counts of a batch: ``preds``/``targets`` are per-image lists of (N, 2) pixel lanes."""
        if len(preds) != len(targets):
            raise ValueError(f"preds has {len(preds)} images but targets has {len(targets)}")
        tp = fp = fn = 0
        for p, g in zip(preds, targets):
            a, b, c = culane_image_counts(list(p), list(g), self.width, self.height, self.lane_width,
                                          self.iou_threshold)
            tp, fp, fn = tp + a, fp + b, fn + c
        self.tp += tp
        self.fp += fp
        self.fn += fn

    def compute(self) -> dict:
        """``culane_summary`` of the accumulated counts."""
        return culane_summary(int(self.tp), int(self.fp), int(self.fn))
