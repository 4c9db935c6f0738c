"""Plots: files written, non-empty PNGs of plausible size; worst_cases picks the largest accuracy drops."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from lanevil_train.report import plots
from tests.report.test_robustness import RECORDS


def _png_shape(path):
    img = cv2.imread(str(path))
    assert img is not None, f"{path} is not a readable image"
    return img.shape


def test_accuracy_vs_severity_png(tmp_path):
    p = plots.score_vs_severity(RECORDS, tmp_path / "a" / "acc.png")
    assert p.is_file() and p.stat().st_size > 5000
    h, w, _ = _png_shape(p)
    assert w > 600 and h > 200  # two model panels side by side
    assert w > h


def test_gap_heatmap_png(tmp_path):
    p = plots.gap_heatmap(RECORDS, tmp_path / "gap.png")
    h, w, _ = _png_shape(p)
    assert p.stat().st_size > 5000 and w > 150 and h > 100


def _with_images(tmp_path, records):
    """Give every record a tiny image file (solid grey) plus one GT and one predicted lane."""
    out = []
    for i, r in enumerate(records):
        path = tmp_path / f"img{i}.png"
        cv2.imwrite(str(path), np.full((24, 40, 3), 90, np.uint8))
        out.append({**r, "image": str(path), "gt_lanes": [[[10, 23], [15, 0]]], "pred_lanes": [[[30, 23], [25, 0]]]})
    return out


def test_worst_cases_selects_the_largest_drops(tmp_path):
    recs = _with_images(tmp_path, RECORDS)
    # drops (clean - perturbed accuracy), the worst per (model, case): A c1 1.0-0.2 = .8 (fence s2),
    # A c2 .8-.4 = .4 (fence s1), B c1 .5-.1 = .4 (fence s2), B c2 .7-.7 = 0 (fence s1)
    top1 = plots.worst_case_pairs(recs, k=1)
    assert [(c["model"], c["case_id"], r["illusion"], r["severity"]) for c, r in top1] == \
        [("A", "c1", "fence_shadow", 2)]
    top3 = plots.worst_case_pairs(recs, k=3)
    assert {(r["model"], r["case_id"]) for _, r in top3} == {("A", "c1"), ("A", "c2"), ("B", "c1")}
    assert top3[0][1]["accuracy"] == 0.2 and top3[0][0]["accuracy"] == 1.0
    assert all(c["severity"] == 0 and c["case_id"] == r["case_id"] for c, r in top3)
    p = plots.worst_cases(recs, tmp_path / "worst.png", k=3)
    h, w, _ = _png_shape(p)
    assert p.stat().st_size > 3000 and h > 500 and w > 400  # three rows of clean | perturbed


def test_draw_colours_gt_green_prediction_red(tmp_path):
    recs = _with_images(tmp_path, RECORDS[:1])
    img = plots._draw(recs[0]["image"], recs[0]["gt_lanes"], recs[0]["pred_lanes"])  # RGB
    assert img.shape == (24, 40, 3)
    green = (img[..., 1] > 200) & (img[..., 0] < 80)
    red = (img[..., 0] > 200) & (img[..., 1] < 80)
    assert green[:, :20].sum() > 10 and green[:, 20:].sum() == 0
    assert red[:, 20:].sum() > 10 and red[:, :20].sum() == 0


def test_worst_cases_skips_without_images(tmp_path):
    assert plots.worst_cases(RECORDS, tmp_path / "w.png") is None
    assert not (tmp_path / "w.png").exists()
    gone = [{**r, "image": str(tmp_path / "missing.png")} for r in RECORDS]
    with pytest.warns(UserWarning, match="not found"):
        assert plots.worst_cases(gone, tmp_path / "w.png") is None
    assert not (tmp_path / "w.png").exists()
