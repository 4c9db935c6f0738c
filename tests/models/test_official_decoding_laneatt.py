"""experiment=official_laneatt_* decodes as the official LaneATT (lucastabelini/LaneATT @ 2f8583b): constructed raw
outputs decoded by our head and written by our prediction files give the TuSimple rows (and CULane points) that
the official decoding gives, written out below from the facts (models/laneatt/official.py): anchors and rows at
f x W, f x H; proposals_to_pred's points; the Lane spline and the writers' truncation; top-k anchors by
torch.argsort on a frequency file with ties."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from scipy.interpolate import InterpolatedUnivariateSpline
from torch import nn

from lanevil_train.evaluation.prediction_files import prediction_fields, tusimple_line
from lanevil_train.lanes import TUSIMPLE_H_SAMPLES, culane_lanes
from lanevil_train.models.detector import LaneDetector
from lanevil_train.models.laneatt import LaneATTHead
from tests.tasks.cli_helpers import composed

IN_H, IN_W, S = 360, 640, 72
IMG_H, IMG_W = 720, 1280
ROW_FRACTIONS = np.linspace(1.0, 0.0, S)  # the official anchor_ys: 1 = the bottom of the image, 0 the top


# ----------------------------------------------------------------- the official decoding, in the test's words
def official_anchor_x(origin: tuple[float, float], angle: float) -> np.ndarray:
    """x (input px) of a line anchor at the S rows: (x0 + (y0 - f) / tan(angle)) x W at row fraction f."""
    x0, y0 = origin
    return (x0 + (y0 - ROW_FRACTIONS) / math.tan(math.radians(angle))) * IN_W


def official_points(xs: np.ndarray, start: int, length: float) -> np.ndarray | None:
    """proposals_to_pred for one proposal: (x, y) as fractions of the input, top first; None under 2 points.
    xs: float32 x (input px) per row, bottom first."""
    xn = (np.asarray(xs, np.float32) / np.float32(IN_W)).astype(np.float64)
    rows = int(torch.round(torch.tensor(length, dtype=torch.float32)))  # decode() rounds the length, halves to even
    last = min(start + rows - 1, S - 1)
    ok = (xn[:start] >= 0) & (xn[:start] <= 1)
    run = np.flip(np.cumprod(np.flip(ok))).astype(bool)  # below the start, inside all the way up to it
    xn[last + 1:] = -2  # a python slice: a negative last + 1 counts from the top row
    below = xn[:start]
    below[~run] = -2
    kept = xn >= 0
    if kept.sum() <= 1:
        return None
    return np.stack([xn[kept], ROW_FRACTIONS[kept]], axis=1)[::-1]


def official_tusimple_row(points: np.ndarray, h_samples=TUSIMPLE_H_SAMPLES) -> list[int]:
    """The Lane spline (k = min(3, n - 1), valid 0.01 past its ends) at h_samples / 720, then x * 1280 truncated,
    -2 where x < 0: the official TuSimple writer's row."""
    ys = np.asarray(h_samples, dtype=np.float64) / IMG_H
    spline = InterpolatedUnivariateSpline(points[:, 1], points[:, 0], k=min(3, len(points) - 1))
    xs = spline(ys)
    xs[(ys < points[:, 1].min() - 0.01) | (ys > points[:, 1].max() + 0.01)] = -2
    out = (xs * IMG_W).astype(int)
    out[xs < 0] = -2
    return out.tolist()


def official_culane_points(points: np.ndarray, img_h: int, img_w: int) -> np.ndarray:
    """The official CULane writer's points of one lane: the spline at every row y / img_h, x in [0, 1), bottom
    first, in pixels."""
    ys = np.arange(img_h) / img_h
    spline = InterpolatedUnivariateSpline(points[:, 1], points[:, 0], k=min(3, len(points) - 1))
    xs = spline(ys)
    xs[(ys < points[:, 1].min() - 0.01) | (ys > points[:, 1].max() + 0.01)] = -2
    valid = (xs >= 0) & (xs < 1)
    return np.stack([xs[valid] * img_w, ys[valid] * img_h], axis=1)[::-1]


# ----------------------------------------------------------------- ours, as experiment=official_laneatt_* builds it
@pytest.fixture(scope="module")
def official_cfg():
    return composed(["experiment=official_laneatt_tusimple", "data.root=/unused",
                     "model.head.anchor_frequency_file=null", "model.head.anchor_selection=all",
                     "model.head.topk_anchors=null"])


@pytest.fixture(scope="module")
def detector(official_cfg):
    """The experiment's head (every anchor), decoding and row sampling, on no backbone."""
    head = instantiate(official_cfg.model.head, in_channels=[512], in_strides=[32], image_size=(IN_H, IN_W))
    return LaneDetector(nn.Identity(), head, decode=dict(official_cfg.model.decode),
                        crop_top=official_cfg.data.crop_top, row_sampling=official_cfg.model.row_sampling)


def anchor_index(head: LaneATTHead, origin: tuple[float, float], angle: float) -> int:
    anchors = head.all_anchors
    near = np.abs(anchors.origins - np.asarray(origin)).sum(axis=1) + np.abs(anchors.angles - angle)
    return int(np.argmin(near))


def our_rows(detector: LaneDetector, raw: dict) -> tuple[list[list[int]], list[np.ndarray]]:
    """Our TuSimple rows (the prediction file's lanes) and lanes (original pixels) of one image's raw outputs."""
    (lanes,) = detector.decode_lanes(raw, (IN_H, IN_W), [(IMG_H, IMG_W)])
    meta = {"height": IMG_H, "width": IMG_W, "h_samples": TUSIMPLE_H_SAMPLES}
    record = {"key": "clips/0/20.jpg", **prediction_fields(lanes, meta, 0.0, detector.row_sampling)}
    return tusimple_line(record)["lanes"], lanes


def one_proposal(head: LaneATTHead, index: int, offsets: np.ndarray, length: float) -> tuple[dict, np.ndarray]:
    """Raw outputs where only anchor `index` is confident, its x the anchor's plus `offsets`; and that x."""
    n = len(head.anchor_starts)
    cls = torch.zeros(1, n, 2)
    cls[0, :, 0] = 10.0
    cls[0, index] = torch.tensor([-10.0, 10.0])
    xs = head.anchor_xs[None].clone()
    xs[0, index] += torch.as_tensor(offsets, dtype=torch.float32)
    lengths = torch.zeros(1, n)
    lengths[0, index] = length
    return {"cls_logits": cls, "length": lengths, "xs": xs}, xs[0, index].numpy()


CASES = {
    # name: (origin, angle, offsets (input px, bottom row first), length)
    "slanted": ((0.55, 1.0), 120.0, 20.0 * ROW_FRACTIONS[::-1] ** 2, 50.0),
    "past_the_right_edge": ((0.8, 1.0), 60.0, 60.0 * ROW_FRACTIONS[::-1], 55.0),  # x > W kept within its rows
    "to_the_left_edge": ((0.25, 1.0), 131.0, np.zeros(S), 60.0),  # leaves at the left, the spline extrapolates
    "extended_below_its_start": ((0.0, 0.7), 39.0, np.full(S, 60.0), 40.0),  # a left anchor, inside below it
    "below_its_start_up_to_x_w": ((1.0, 0.6), 141.0, np.full(S, -3.0), 30.0),
    "top_within_the_margin": ((0.5, 1.0), 100.0, np.zeros(S), 33.0),
    "half_a_row_rounds_to_even": ((0.45, 1.0), 80.0, np.zeros(S), 40.5),
    "a_length_of_minus_one_keeps_all_but_the_top_row": ((0.35, 1.0), 90.0, np.zeros(S), -1.0),
}


def test_the_experiment_sets_the_official_geometry_decoding_and_writer(official_cfg):
    assert official_cfg.model.head.fraction_scale == "size"
    assert official_cfg.model.decode.lane_points == "official"
    assert official_cfg.model.row_sampling == "spline"
    for dataset, rows in (("culane", [0, 590, 1]), ("llamas", [0, 717, 1])):
        cfg = composed([f"experiment=official_laneatt_{dataset}", "data.root=/unused"])
        assert list(cfg.model.culane_rows) == rows and cfg.model.row_sampling == "spline"
    own = composed(["model=laneatt"])  # this project's own: the documented defaults
    assert own.model.head.get("fraction_scale", "last_pixel") == "last_pixel"
    assert own.model.decode.get("lane_points", "inside") == "inside"


def test_anchors_and_rows_are_the_officials(detector):
    head = detector.head
    np.testing.assert_allclose(head.row_ys, ROW_FRACTIONS * IN_H, atol=1e-9)  # y = 360 .. 0
    for origin, angle in [((0.0, 0.5), 49.0), ((0.3, 1.0), 165.0), ((1.0, 0.2), 150.0), ((0.9, 1.0), 15.0)]:
        k = anchor_index(head, origin, angle)
        x0, y0 = head.all_anchors.origins[k]
        np.testing.assert_allclose(head.anchor_xs[k].numpy(), official_anchor_x((x0, y0), angle), atol=1e-3)


@pytest.mark.parametrize("case", list(CASES))
def test_a_proposal_gives_the_official_tusimple_row(detector, case):
    origin, angle, offsets, length = CASES[case]
    head = detector.head
    k = anchor_index(head, origin, angle)
    raw, xs = one_proposal(head, k, offsets, length)
    points = official_points(xs, int(head.anchor_starts[k]), length)
    rows, _ = our_rows(detector, raw)
    assert rows == [official_tusimple_row(points)]
    row = np.asarray(rows[0])
    if case == "past_the_right_edge":
        assert (row >= IMG_W).sum() >= 3  # written past the right edge, as the official
    if case == "to_the_left_edge":
        top = np.argmax(row >= 0)
        assert top > 0 and 0 <= row[top] < 40  # it ends at the left edge inside the rows
    if case == "extended_below_its_start":
        start_y = (1 - ROW_FRACTIONS[int(head.anchor_starts[k])]) * IMG_H
        assert np.nanmax(np.where(row >= 0, TUSIMPLE_H_SAMPLES, np.nan)) > start_y + 20
    if case == "top_within_the_margin":
        top_y = points[:, 1].min() * IMG_H
        first = TUSIMPLE_H_SAMPLES[np.argmax(row >= 0)]
        assert top_y - 0.01 * IMG_H <= first < top_y  # a row above the lane's top point, inside the margin
    if case == "half_a_row_rounds_to_even":
        assert len(points) == 40  # 40.5 -> 40 rows
    if case == "a_length_of_minus_one_keeps_all_but_the_top_row":
        assert len(points) == S - 1


def test_the_culane_writer_gives_the_official_points():
    """A lane through official_experiment's CULane rows: each image row, the spline unrounded, x in [0, W)."""
    cfg = composed(["experiment=official_laneatt_culane", "data.root=/unused"])
    img_h, img_w = 590, 1640
    fractions = np.stack([np.linspace(0.3, 1.02, 20), np.linspace(0.55, 1.0, 20)], axis=1)  # leaves at the right
    fractions[:, 0] += 0.02 * np.sin(np.arange(20))
    ours = culane_lanes([fractions * [img_w, img_h]], cfg.model.culane_rows, cfg.model.row_sampling, img_h, img_w)
    official = official_culane_points(fractions, img_h, img_w)
    assert len(ours) == 1 and ours[0].shape == official.shape
    np.testing.assert_allclose(ours[0], official, atol=1e-6)


def test_a_frequency_file_with_ties_keeps_the_anchors_torch_argsort_keeps(tmp_path):
    counts = torch.tensor([int(3000 / (1 + rank / 10)) for rank in range(2784)], dtype=torch.int32)
    counts = counts[torch.randperm(2784, generator=torch.Generator().manual_seed(0))]
    torch.save(counts, tmp_path / "tusimple_anchors_freq.pt")
    official = torch.argsort(counts, descending=True)[:1000]
    stable = np.argsort(-counts.numpy(), kind="stable")[:1000]
    assert set(stable.tolist()) != set(official.tolist())  # the ties reach the cut: the order matters
    head = LaneATTHead([512], [32], (IN_H, IN_W), anchor_selection="frequency", topk_anchors=1000,
                       fraction_scale="size", anchor_frequency_file=str(tmp_path / "tusimple_anchors_freq.pt"))
    assert head.anchor_index.tolist() == official.tolist()
