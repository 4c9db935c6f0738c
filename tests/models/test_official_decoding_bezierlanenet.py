"""BezierLaneNet's official TuSimple decoding (experiment=official_bezierlanenet_tusimple): constructed existence
logits and curves decoded by our head with the experiment's decode settings, mapped to the original image as
LaneDetector does and written as the TuSimple prediction file writes them, against pytorch-auto-drive's decoding
written out here from the facts (models/bezierlanenet/bezier.py and official.py: bezier_base.py l. 18-95 at 137e63a):
sigmoid > 0.5 and the leftmost maximum of its 9-query window, at most 5 (the least confident of all dropped, equal
ones together); each curve sampled at 720 values of t evenly spaced in [0, 1]; on row 1 - (56 - i) * 10 / 720 (as
float32) the sample nearest in y gives x * 1280 unless it is more than 5 / 720 away in y or x is outside [0, 1]
(-2)."""

from __future__ import annotations

from math import comb
from types import SimpleNamespace

import numpy as np
import torch
from torch.nn import functional as F

from lanevil_train.evaluation.prediction_files import prediction_fields, tusimple_line
from lanevil_train.models.bezierlanenet import BezierLaneNetHead
from lanevil_train.models.detector import LaneDetector
from tests.tasks.cli_helpers import composed

QUERIES = 40  # 640 px / 16


def official_kept(logits: torch.Tensor, max_lane: int = 5) -> np.ndarray:
    conf = logits.sigmoid()
    exist = conf > 0.5
    _, idx = F.max_pool1d(conf[:, None], kernel_size=9, stride=1, padding=4, return_indices=True)
    exist &= idx[:, 0] == torch.arange(conf.shape[1])[None]
    conf = conf.clone()
    while (exist.sum(1) > max_lane).any():
        lowest = (exist.sum(1, keepdim=True) > max_lane) & (conf == conf.min(1, keepdim=True).values)
        exist[lowest] = False
        conf[lowest] = 1.1
    return exist.numpy()


def official_rows(control_points: np.ndarray) -> list[float]:
    """One curve's x at the 56 rows of the 1280x720 image, -2 where none."""
    ts = np.linspace(0.0, 1.0, 720)
    samples = np.array([[t ** k * (1 - t) ** (3 - k) * comb(3, k) for k in range(4)] for t in ts]) @ control_points
    rows = np.array([1.0 - (56 - i) * 10 / 720 for i in range(56)], dtype=np.float32)
    out = []
    for row in rows:
        distance = np.abs(row - samples[:, 1])
        j = int(distance.argmin())
        x = samples[j, 0]
        out.append(-2.0 if distance[j] > 5.0 / 720 or x > 1 or x < 0 else float(x) * 1280)
    return out


def ours(raw: dict) -> list[list[float]]:
    cfg = composed(["experiment=official_bezierlanenet_tusimple", "data.root=/unused"])
    head = BezierLaneNetHead([256], [16], (360, 640))
    model = SimpleNamespace(head=head, decode_kwargs=dict(cfg.model.decode), crop_top=float(cfg.data.crop_top))
    lanes = LaneDetector.decode_lanes(model, raw, (360, 640), [(720, 1280)])[0]
    meta = {"height": 720, "width": 1280, "h_samples": list(range(160, 720, 10))}
    return tusimple_line({**prediction_fields(lanes, meta, 0.0, cfg.model.row_sampling), "key": "x"})["lanes"]


def curve(bottom, top, bend=0.0, mid_x=None):
    """Control points (4, 2), normalised: from bottom (x, y) to top (x, y), the inner two bent by `bend` in x."""
    (x0, y0), (x3, y3) = bottom, top
    inner = [(x0 + (x3 - x0) * t + bend, y0 + (y3 - y0) * t) for t in (1 / 3, 2 / 3)]
    if mid_x is not None:
        inner = [(mid_x, y) for _, y in inner]
    return [(x0, y0), *inner, (x3, y3)]


def constructed(confidences: dict[int, float]) -> dict:
    logits = torch.full((1, QUERIES), -6.0)
    curves = np.tile(np.array(curve((0.5, 1.05), (0.5, 0.4)), dtype=np.float32), (1, QUERIES, 1, 1))
    shapes = {
        1: curve((-0.3, 1.04), (0.45, 0.38)),        # leaves at the left edge
        8: curve((0.3, 0.97), (0.48, 0.43)),        # ends 2 rows above the bottom and between two rows at the top
        15: curve((0.62, 1.1), (0.52, 0.36), mid_x=-0.2),  # its x leaves [0, 1] in the middle: -2 inside
        22: curve((1.35, 1.02), (0.55, 0.37)),       # past the right edge
        29: curve((0.8, 1.0), (0.5, 0.4), bend=0.2),  # bent: the nearest sample and the row differ most
    }
    for q, cps in shapes.items():
        curves[0, q] = cps
    for q, value in confidences.items():
        logits[0, q] = float(np.log(value / (1 - value)))
    return {"logits": logits, "curves": torch.tensor(curves)}


def official(raw: dict) -> list[list[float]]:
    kept = official_kept(raw["logits"])[0]
    cps = raw["curves"][0].double().numpy()
    lanes = [official_rows(cps[q]) for q in np.flatnonzero(kept)]
    return [lane for lane in lanes if sum(x >= 0 for x in lane) >= 2]


def assert_same_rows(mine: list[list[float]], theirs: list[list[float]]) -> None:
    assert len(mine) == len(theirs)
    for a, b in zip(sorted(mine), sorted(theirs)):
        a, b = np.asarray(a), np.asarray(b)
        assert ((a >= 0) == (b >= 0)).all()  # the same -2 samples
        assert np.abs(a[a >= 0] - b[b >= 0]).max() <= 0.005 + 1e-9  # x written to 0.01 px


def test_the_official_writers_points():
    raw = constructed({1: 0.9, 8: 0.8, 15: 0.85, 22: 0.7, 29: 0.95})
    mine, theirs = ours(raw), official(raw)
    assert_same_rows(mine, theirs)
    assert len(mine) == 5
    def inner_gap(lane):  # -2 between two points
        points = [i for i, x in enumerate(lane) if x >= 0]
        return any(lane[i] == -2 for i in range(points[0], points[-1]))

    assert any(inner_gap(lane) for lane in mine)  # x leaves the image and comes back
    assert any(lane[-1] == -2 and lane[-2] >= 0 for lane in mine)  # ends between the last two rows
    assert any(max(lane) > 1250 and lane[lane.index(max(lane)) + 1] == -2 for lane in mine)  # out at the right


def test_equal_confidences_at_the_lowest_are_dropped_together():
    raw = constructed({1: 0.9, 8: 0.8, 15: 0.85, 22: 0.7, 29: 0.95, 36: 0.7})  # 6 lanes, two at 0.7
    theirs = official(raw)
    assert len(theirs) == 4
    assert_same_rows(ours(raw), theirs)


def test_the_official_culane_writers_points():
    """experiment=official_bezierlanenet_culane: existence above 0.95, at most 4 lanes, each curve's 50 samples at
    t = linspace(0, 1, 50) times 1640 x 590, every one written, inside the image or not (bezier_base.py l. 43-47,
    84-85; lane_det_tester.py l. 59-69)."""
    cfg = composed(["experiment=official_bezierlanenet_culane", "data.root=/unused"])
    queries = 800 // 16
    head = BezierLaneNetHead([256], [16], (288, 800))
    model = SimpleNamespace(head=head, decode_kwargs=dict(cfg.model.decode), crop_top=float(cfg.data.crop_top))
    logits = torch.full((1, queries), -6.0)
    curves = np.tile(np.array(curve((0.5, 1.05), (0.5, 0.4)), dtype=np.float32), (1, queries, 1, 1))
    shapes = {2: curve((-0.3, 1.04), (0.45, 0.38)), 12: curve((0.3, 0.97), (0.48, 0.43), bend=0.1),
              22: curve((1.35, 1.02), (0.55, 0.37)), 32: curve((0.8, 1.0), (0.5, 0.4), bend=0.2),
              42: curve((0.9, 1.0), (0.6, 0.45))}
    for q, cps in shapes.items():
        curves[0, q] = cps
    for q, p in {2: 0.99, 12: 0.97, 22: 0.999, 32: 0.96, 42: 0.955}.items():
        logits[0, q] = float(np.log(p / (1 - p)))
    raw = {"logits": logits, "curves": torch.tensor(curves)}
    lanes = LaneDetector.decode_lanes(model, raw, (288, 800), [(590, 1640)])[0]
    ts = np.linspace(0.0, 1.0, 50)
    basis = np.array([[t ** k * (1 - t) ** (3 - k) * comb(3, k) for k in range(4)] for t in ts])
    kept = [2, 12, 22, 32]  # 42, the least confident of five, pruned (max_lane 4)
    theirs = [basis @ np.asarray(curves[0, q], dtype=np.float64) * np.array([1640.0, 590.0]) for q in kept]
    assert len(lanes) == 4 and all(len(lane) == 50 for lane in lanes)
    mine = sorted((lane[np.argsort(lane[:, 1])] for lane in lanes), key=lambda lane: lane[0, 0])
    theirs = sorted((lane[np.argsort(lane[:, 1])] for lane in theirs), key=lambda lane: lane[0, 0])
    for a, b in zip(mine, theirs):
        np.testing.assert_allclose(a, b, atol=1e-6)
    assert min(lane[:, 0].min() for lane in mine) < 0 and max(lane[:, 0].max() for lane in mine) > 1640  # kept
    assert max(lane[:, 1].max() for lane in mine) > 590  # below the image too
