"""Cubic Bezier curves for BezierLaneNet (Feng et al., CVPR 2022): the Bernstein basis, the least-squares fit of
control points to a lane's points, sampling a curve at t values and at image rows, and cutting a curve to a span of
t (the in-image segment).

A curve of order n is B(t) = sum_k C(n, k) t^k (1 - t)^(n - k) P_k, t in [0, 1], with control points P_k (x, y).
As the official code, a lane is fitted with t the normalised chord length along its points (the cumulative
distance between consecutive points over the total), by least squares (the pseudo-inverse of the Bernstein matrix).
Functions take numpy arrays or torch tensors (``bernstein`` and ``sample_bezier`` keep the type of their input;
the others are numpy, for the target encoder in data workers and for decoding).

``official_tusimple_points``: the points pytorch-auto-drive's TuSimple writer gives a curve (voldemortX/
pytorch-auto-drive at 137e63a, ``utils/models/lane_detection/bezier_base.py`` l. 18-42 and 83-91,
``utils/curve_utils.py`` l. 49-103, the test dict of ``configs/lane_detection/bezierlanenet/
resnet{18,34}_tusimple_aug1b.py`` l. 46-52: gap=10, ppl=56, original_size=(720, 1280)): the curve (control points
normalised by the input's width and height, float64) sampled at H = 720 values of t, ``numpy.linspace(0, 1, H)``
(``BezierCurve(order=3, num_sample_points=H)``, the Bernstein row of t being ``t ** k * (1 - t) ** (3 - k) *
comb(3, k)``, the sample the matrix product with the control points); the rows ``1 - (ppl - i) * gap / H`` as
float32; per row the sample nearest in y (the first of equals), no point where it is more than 5 / H away in y or
its x is outside [0, 1]; else x = its x times W, written at y = H - (ppl - i) * gap (160, 170, ..., 710).

``official_culane_points``: the points its CULane writer gives a curve (bezier_base.py l. 43-47 and 84-85:
``BezierCurve(order=3, num_sample_points=n)`` with n = 50 for CULane, l. 54; utils/runners/lane_det_tester.py
l. 59-69): the curve sampled at ``numpy.linspace(0, 1, 50)`` values of t, x times W and y times H of the original
1640x590 image, every sample written, inside the image or not.
"""

from __future__ import annotations

from math import comb

import numpy as np
import torch

ORDER = 3  # the paper's cubic curves: 4 control points
# The official TuSimple writer's image (its test config's original_size), row spacing, rows and y tolerance in pixels
OFFICIAL_TUSIMPLE_SIZE = (720, 1280)
OFFICIAL_CULANE_SIZE, OFFICIAL_CULANE_SAMPLES = (590, 1640), 50
OFFICIAL_TUSIMPLE_GAP, OFFICIAL_TUSIMPLE_ROWS, OFFICIAL_TUSIMPLE_TOLERANCE = 10, 56, 5.0


def bernstein(ts, order: int = ORDER):
    """The Bernstein basis (len(ts), order + 1) at parameters ts (a 1-D array or tensor; the type is kept)."""
    if isinstance(ts, torch.Tensor):
        t = ts.reshape(-1, 1)
        k = torch.arange(order + 1, dtype=t.dtype, device=t.device)
        coeff = torch.tensor([comb(order, int(i)) for i in range(order + 1)], dtype=t.dtype, device=t.device)
        return coeff * t**k * (1 - t) ** (order - k)
    t = np.asarray(ts, dtype=np.float64).reshape(-1, 1)
    k = np.arange(order + 1)
    coeff = np.array([comb(order, int(i)) for i in k], dtype=np.float64)
    return coeff * t**k * (1 - t) ** (order - k)


def sample_bezier(control_points, ts):
    """Points (..., len(ts), 2) of curves with control points (..., order + 1, 2) at parameters ts."""
    basis = bernstein(ts, control_points.shape[-2] - 1)
    if isinstance(control_points, torch.Tensor):
        return torch.matmul(basis.to(control_points.dtype), control_points)
    return np.matmul(basis, np.asarray(control_points, dtype=np.float64))


def chord_length_params(points: np.ndarray) -> np.ndarray:
    """t of each point (N, 2): the cumulative chord length from the first point over the total, in [0, 1]."""
    points = np.asarray(points, dtype=np.float64)
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    total = steps.sum()
    if total <= 0:
        raise ValueError("chord_length_params: the points all coincide; a curve through them is undefined")
    return np.concatenate([[0.0], np.cumsum(steps) / total])


def fit_bezier(points: np.ndarray, order: int = ORDER, ts: np.ndarray | None = None) -> np.ndarray:
    """Control points (order + 1, 2) of the least-squares Bezier curve through points (N, 2), N >= 2, in their
    order, at parameters ts (default: their chord-length parameters, as the official). Fewer than order + 1 points
    are first densified along their polyline (linear interpolation), so two points give a straight segment, not the
    pseudo-inverse's minimum-norm curve."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2 or len(points) < 2:
        raise ValueError(f"fit_bezier: expected (N >= 2, 2) points, got shape {points.shape}")
    ts = chord_length_params(points) if ts is None else np.asarray(ts, dtype=np.float64)
    if ts.shape != (len(points),):
        raise ValueError(f"fit_bezier: {len(points)} points but ts of shape {ts.shape}")
    if len(points) < order + 1:
        dense = np.linspace(0.0, 1.0, order + 1)
        points = np.stack([np.interp(dense, ts, points[:, 0]), np.interp(dense, ts, points[:, 1])], axis=1)
        ts = dense
    return np.linalg.pinv(bernstein(ts, order)) @ points


def sub_curve(control_points: np.ndarray, t0: float, t1: float) -> np.ndarray:
    """Control points of the part of a curve between t0 and t1 (the same curve, reparametrised to [0, 1]).

    B(t0 + (t1 - t0) s) is a polynomial of the same order in s, so fitting it at order + 1 distinct s is exact (the
    official derives the same linear map by De Casteljau's algorithm)."""
    cps = np.asarray(control_points, dtype=np.float64)
    order = cps.shape[-2] - 1
    s = np.linspace(0.0, 1.0, order + 1)
    return np.linalg.solve(bernstein(s, order), sample_bezier(cps, t0 + (t1 - t0) * s))


def x_at_rows(control_points: np.ndarray, ys: np.ndarray, num_samples: int = 200,
              tolerance: float = 0.0) -> np.ndarray:
    """x of a curve (control points in pixels) at each row in ys, by linear interpolation between num_samples
    points sampled along it; NaN for rows more than `tolerance` outside its y span (rows within it read the
    nearest end's x). A curve that turns back in y is read as the points sorted by y (its rows then come from one
    of its branches)."""
    pts = sample_bezier(np.asarray(control_points, dtype=np.float64), np.linspace(0.0, 1.0, num_samples))
    ys = np.asarray(ys, dtype=np.float64)
    order = np.argsort(pts[:, 1], kind="stable")
    py, px = pts[order, 1], pts[order, 0]
    out = np.full(ys.shape, np.nan)
    inside = (ys >= py[0] - tolerance) & (ys <= py[-1] + tolerance)
    out[inside] = np.interp(ys[inside], py, px)
    return out


def _official_samples(control_points: np.ndarray, count: int) -> np.ndarray:
    """The curve at numpy.linspace(0, 1, count) values of t, as the official BezierCurve.quick_sample_point."""
    ts = np.linspace(0.0, 1.0, count)
    basis = np.array([[t ** k * (1 - t) ** (ORDER - k) * comb(ORDER, k) for k in range(ORDER + 1)] for t in ts])
    return basis.dot(np.asarray(control_points, dtype=np.float64))


def official_culane_points(control_points: np.ndarray) -> np.ndarray:
    """The points (50, 2) the official CULane writer gives a curve (control points (4, 2) normalised by the input's
    width and height), in its 1640x590 image, in the order of t (module docstring)."""
    big_h, big_w = OFFICIAL_CULANE_SIZE
    return _official_samples(control_points, OFFICIAL_CULANE_SAMPLES) * np.array([big_w, big_h])


def official_tusimple_points(control_points: np.ndarray) -> np.ndarray:
    """The points (N, 2) the official TuSimple writer gives a curve (control points (4, 2) normalised by the input's
    width and height), in its 1280x720 image: its rows with a point, top first (module docstring)."""
    big_h, big_w = OFFICIAL_TUSIMPLE_SIZE
    gap, ppl = OFFICIAL_TUSIMPLE_GAP, OFFICIAL_TUSIMPLE_ROWS
    samples = _official_samples(control_points, big_h)
    rows = np.array([1.0 - (ppl - i) * gap / big_h for i in range(ppl)], dtype=np.float32)
    distance = np.abs(rows[:, None] - samples[:, 1])
    nearest = distance.argmin(axis=1)
    xs = samples[nearest, 0]
    valid = ~(distance[np.arange(ppl), nearest] > OFFICIAL_TUSIMPLE_TOLERANCE / big_h) & ~(xs > 1) & ~(xs < 0)
    ys = np.array([big_h - (ppl - i) * gap for i in range(ppl)], dtype=np.float64)
    return np.stack([xs[valid] * big_w, ys[valid]], axis=1)
