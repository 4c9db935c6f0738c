"""CurveLanes F1: hand counts at the 224x224 evaluation size, a literal per-pair reading of it, the command."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from lanevil_train.metrics.__main__ import main
from lanevil_train.metrics.curvelanes import curvelanes_image_counts, kit_samples

SIZE = (1440, 2560)  # (H, W) of most CurveLanes images; 1 evaluation px = 2560 / 224 = 11.43 image px across


def _vertical(x_eval: float, size=SIZE, top=40.5, bottom=223.5) -> np.ndarray:
    """A straight vertical lane at evaluation x (away from integer edges, so truncation is unambiguous), in image px."""
    h, w = size
    return np.array([[x_eval * w / 224, bottom * h / 224], [x_eval * w / 224, top * h / 224]])


def test_the_drawn_width_and_the_hand_counts_at_224():
    # cv2.line of thickness 5 covers 7 columns of a vertical line: two lanes d columns apart share 7 - d of them,
    # IoU ~ (7 - d) / (7 + d) (the round caps add a little): d = 2 gives 0.56 (a hit), d = 3 gives 0.40 (a miss)
    canvas = np.zeros((224, 224), np.uint8)
    cv2.line(canvas, (100, 200), (100, 50), 255, 5)
    assert (canvas[120] > 0).sum() == 7
    gt = [_vertical(112.5)]
    assert curvelanes_image_counts([_vertical(112.5)], gt, SIZE) == (1, 0, 0)
    assert curvelanes_image_counts([_vertical(114.5)], gt, SIZE) == (1, 0, 0)  # 22.9 px off at 2560 wide
    assert curvelanes_image_counts([_vertical(115.5)], gt, SIZE) == (0, 1, 1)  # 34.3 px off
    # the scaling is per axis: the same 3 evaluation columns are 21 px on a 1570x660 image
    small = (660, 1570)
    assert curvelanes_image_counts([_vertical(115.5, small)], [_vertical(112.5, small)], small) == (0, 1, 1)
    assert curvelanes_image_counts([_vertical(114.5, small)], [_vertical(112.5, small)], small) == (1, 0, 0)


def test_nine_lanes_matched_one_to_one():
    gt = [_vertical(20.5 + 22 * i) for i in range(9)]
    preds = [_vertical(21.5 + 22 * i) for i in range(7)] + [_vertical(213.5, top=150.5), _vertical(5.5, bottom=60.5)]
    # 7 hits; the 2 extra lanes overlap nothing enough (the short one on lane 9's column has IoU < 0.5)
    assert curvelanes_image_counts(preds, gt, SIZE) == (7, 2, 2)
    assert curvelanes_image_counts([], gt, SIZE) == (0, 0, 9)
    assert curvelanes_image_counts(preds, [], SIZE) == (0, 9, 0)
    # a lane of one point counts but never hits; repeated points do not break the spline
    dup = np.repeat(_vertical(20.5), 2, axis=0)
    assert curvelanes_image_counts([dup, np.array([[5.0, 5.0]]), np.zeros((0, 2))], gt[:1], SIZE) == (1, 1, 0)


def test_spline_samples_one_per_evaluation_pixel_of_chord():
    s = kit_samples(np.array([[0.0, 0.0], [3.0, 4.0], [6.0, 0.0]]))  # two chords of 5: t = 0..4 each, then the end
    assert len(s) == 11
    np.testing.assert_allclose(s[[0, 5, 10]], [[0, 0], [3, 4], [6, 0]], atol=1e-12)  # through every point
    np.testing.assert_allclose(kit_samples(np.array([[0.0, 0.0], [0.0, 2.5]])), [[0, 0], [0, 1], [0, 2], [0, 2.5]])


def _literal_counts(pred, gt, size, lane_width=5, thr=0.5):
    """The procedure read literally: the natural spline solved per lane as a dense linear system, every pair drawn
    on fresh canvases with one cv2.line per pair of consecutive samples."""

    def samples(lane):
        p = [tuple(pt) for i, pt in enumerate(lane) if i == 0 or tuple(pt) != tuple(lane[i - 1])]
        p = np.array(p, float)
        if len(p) < 2:
            return [tuple(q) for q in p]
        h = np.hypot(*np.diff(p, axis=0).T)
        n, out = len(p), []
        m = np.zeros((n, 2))
        if n > 2:
            mat, rhs = np.zeros((n - 2, n - 2)), np.zeros((n - 2, 2))
            for i in range(n - 2):
                mat[i, i] = 2 * (h[i] + h[i + 1])
                if i > 0:
                    mat[i, i - 1] = h[i]
                if i < n - 3:
                    mat[i, i + 1] = h[i + 1]
                rhs[i] = 6 * ((p[i + 2] - p[i + 1]) / h[i + 1] - (p[i + 1] - p[i]) / h[i])
            m[1:-1] = np.linalg.solve(mat, rhs)
        for i in range(n - 1):
            b = (p[i + 1] - p[i]) / h[i] - (2 * h[i] * m[i] + h[i] * m[i + 1]) / 6
            c, d = m[i] / 2, (m[i + 1] - m[i]) / (6 * h[i])
            t = 0.0
            while t < h[i]:
                out.append(tuple(p[i] + b * t + c * t * t + d * t * t * t))
                t += 1
        return out + [tuple(p[-1])]

    def mask(lane):
        im = np.zeros((224, 224), np.uint8)
        pts = samples(np.asarray(lane, float) / np.array([size[1] / 224, size[0] / 224]))
        for (x0, y0), (x1, y1) in zip(pts[:-1], pts[1:]):
            cv2.line(im, (int(x0), int(y0)), (int(x1), int(y1)), 255, lane_width)
        return im > 0

    if not pred or not gt:
        return 0, len(pred), len(gt)
    ious = np.zeros((len(gt), len(pred)))
    for i, g in enumerate(gt):
        for j, p in enumerate(pred):
            a, b = mask(g), mask(p)
            union = (a | b).sum()
            ious[i, j] = (a & b).sum() / union if union else 0.0
    rows, cols = linear_sum_assignment(1 - ious)
    tp = int((ious[rows, cols] > thr).sum())
    return tp, len(pred) - tp, len(gt) - tp


def test_agrees_with_a_literal_reading_on_random_curves():
    rng = np.random.default_rng(3)
    for k in range(12):
        size = [(1440, 2560), (660, 1570), (720, 1280)][k % 3]
        h, w = size
        gt, pred = [], []
        for _ in range(rng.integers(1, 5)):
            ys = np.sort(rng.uniform(0.35 * h, h, rng.integers(2, 7)))[::-1]
            xs = rng.uniform(0, w) + np.cumsum(rng.normal(0, 0.05 * w, len(ys)))
            gt.append(np.stack([xs, ys], 1))
            pred.append(gt[-1] + np.array([rng.normal(0, 25), 0]))
        assert curvelanes_image_counts(pred, gt, size) == _literal_counts(pred, gt, size)


def _tree(root: Path) -> Path:
    """Two valid images (2560x1440 and 1570x660 headers) with labels; predictions under pred/valid/images."""
    folder = root / "data" / "valid"
    (folder / "images").mkdir(parents=True)
    (folder / "labels").mkdir()
    (folder / "valid.txt").write_text("images/a.jpg\nimages/b.jpg\n")
    for name, size, xs in (("a", SIZE, [112.5, 150.5]), ("b", (660, 1570), [60.5])):
        assert cv2.imwrite(str(folder / "images" / f"{name}.jpg"), np.zeros((*size, 3), np.uint8))
        lanes = [[{"x": str(x), "y": str(y)} for x, y in _vertical(x, size)] for x in xs]
        (folder / "labels" / f"{name}.lines.json").write_text(json.dumps({"Lines": lanes}))
    pred = root / "pred" / "valid" / "images"
    pred.mkdir(parents=True)
    # a: one hit (1 column off), one miss (4 columns off); b: one hit and an extra lane
    lines = {"a": [_vertical(113.5), _vertical(154.5)], "b": [_vertical(60.5, (660, 1570)),
                                                              _vertical(200.5, (660, 1570))]}
    for name, lanes in lines.items():
        (pred / f"{name}.lines.txt").write_text("".join(" ".join(f"{v:.3f}" for v in lane.ravel()) + "\n"
                                                        for lane in lanes))
    return root


def test_the_command_scores_a_tree(tmp_path, capsys):
    root = _tree(tmp_path)
    assert main(["curvelanes", "--pred-dir", str(root / "pred"), "--root", str(root / "data")]) == 0
    result = json.loads(capsys.readouterr().out)
    assert (result["TP"], result["FP"], result["FN"], result["images"]) == (2, 2, 1, 2)
    assert result["F1"] == pytest.approx(2 * 0.5 * (2 / 3) / (0.5 + 2 / 3))
    # every image taken as 1280 wide: a's lanes (x > 1280) then fall off the 224 px canvas, and its hit is lost
    assert main(["curvelanes", "--pred-dir", str(root / "pred"), "--root", str(root / "data"),
                 "--image-size", "1280x1440"]) == 0
    assert json.loads(capsys.readouterr().out)["TP"] == 1


def test_the_command_names_bad_input(tmp_path, capsys):
    root = _tree(tmp_path)
    label = root / "data" / "valid" / "labels" / "b.lines.json"
    label.write_text(json.dumps({"Lines": [[{"x": "1", "y": "oops"}, {"x": 1, "y": 2}]]}))
    assert main(["curvelanes", "--pred-dir", str(root / "pred"), "--root", str(root / "data")]) == 1
    assert f"error: {label}: Lines[0][0].y: expected a number" in capsys.readouterr().err
    assert main(["curvelanes", "--pred-dir", str(root / "nothing"), "--root", str(root / "data")]) == 1
    assert "is not a directory" in capsys.readouterr().err
    assert main(["curvelanes", "--pred-dir", str(root / "pred"), "--root", str(root / "data"), "--split", "test"]) == 1
    assert "the test split's labels are not public" in capsys.readouterr().err

