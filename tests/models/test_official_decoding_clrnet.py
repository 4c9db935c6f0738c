"""CLRNet's decoding writes the TuSimple rows the official code writes (Turoad/CLRNet at 7269e9d): constructed raw
outputs decoded by our head (``lane_points: official``), mapped to the original image as LaneDetector does and
written as our TuSimple file writes them (``row_sampling: spline``), against the official decoding written out
here from its facts (models/clrnet/official.py, "Decoding"): lanes past the right edge, ending near the left
edge, leaving it before their end, dipping out of the image and back, extended down, a half-even length and a
negative one; and the same predictions in CULane's image as the official CULane writer writes them."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy.interpolate import InterpolatedUnivariateSpline

from lanevil_train.evaluation.prediction_files import prediction_fields, tusimple_line
from lanevil_train.lanes import culane_lanes
from lanevil_train.models.clrnet import CLRNetHead
from lanevil_train.models.detector import LaneDetector

IN_H, IN_W, ORI_H, ORI_W, CUT = 320, 800, 720, 1280, 160
CULANE_H, CULANE_W, CULANE_CUT = 590, 1640, 270
N_POINTS = 72
N_STRIPS = N_POINTS - 1
H_SAMPLES = list(range(160, 720, 10))
F = np.arange(N_POINTS) / N_STRIPS  # height of each row above the bottom row, as a fraction


def _case(frac, start_y, length):
    """A prediction; its x slightly bent and shifted off round values, so that no written x lies within
    NEAR_INTEGER of a whole pixel (where the 1e-4 px the records keep could truncate it the other way)."""
    frac = np.asarray(frac, dtype=np.float64) + 0.0031 * F ** 2 + np.sqrt(2) * 1e-4
    return {"frac": frac.astype(np.float32), "start_y": np.float32(start_y), "length": np.float32(length)}


NEAR_INTEGER = 1e-3  # px


# x as the official's fraction of W-1 at the 72 rows (bottom first), start_y, length (fractions of the 71 strips)
CASES = {
    "past the right edge": _case(0.55 + 0.62 * F, 0.0, 0.9),
    "ends near the left edge": _case(0.004 + 0.9 * (F - 0.05), 0.05, 0.6),
    "leaves the left edge before its end": _case(0.06 - 0.14 * (F - 0.1), 0.1, 0.45),
    "dips out of the image and back": _case(-0.01 + 0.5 * (F - 0.35) ** 2, 0.0, 0.8),
    "extended down, half-even length": _case(0.45 + 0.02 * F, 0.22, 10.5 / 71),
    "negative length": _case(0.7 - 0.1 * F, 0.0, -3 / 71),
    "starts right of the right edge": _case(1.02 - 0.3 * (F - 0.05), 0.05, 0.75),
}


def official_lane(frac: np.ndarray, start_y: np.float32, length: np.float32, ori_h: int, cut: int):
    """The official Lane of one kept prediction (None: dropped) as (spline, lowest and highest y normalised by the
    original height), from the facts: clr_head.py:477 and 279-319 (start, length, end, the kept rows, the y mapping
    over the original height below the cut), utils/lane.py:5-28 (the spline through its points)."""
    xs = torch.from_numpy(frac.copy())
    length_rows = torch.round(torch.tensor(length) * N_STRIPS).item()  # float32, half to even
    start = min(max(0, int(round(float(start_y) * N_STRIPS))), N_STRIPS)  # Python's round on the double
    end = min(start + int(round(length_rows)) - 1, N_STRIPS)
    inside_below = ((xs[:start] >= 0) & (xs[:start] <= 1)).numpy()
    still_inside = inside_below[::-1].cumprod()[::-1].astype(bool)
    xs[end + 1:] = -2  # a Python slice: a negative end + 1 counts from the top row
    xs[:start][torch.from_numpy(~still_inside)] = -2
    heights = torch.linspace(1, 0, N_POINTS, dtype=torch.float32).double()
    ys = heights[xs >= 0].flip(0)
    xs = xs[xs >= 0].flip(0).double()
    ys = (ys * (ori_h - cut) + cut) / ori_h
    if len(xs) <= 1:
        return None
    spline = InterpolatedUnivariateSpline(ys.numpy(), xs.numpy(), k=min(3, len(xs) - 1))
    return spline, ys.min().item(), ys.max().item()


def lane_values(lane, samples: np.ndarray) -> np.ndarray:
    """The Lane called at normalised rows: its spline, -2 beyond 0.01 past its lowest and highest point."""
    spline, low, high = lane
    values = spline(samples)
    values[(samples < low - 0.01) | (samples > high + 0.01)] = -2
    return values


def official_tusimple_lane(frac: np.ndarray, start_y: np.float32, length: np.float32):
    """The official TuSimple row values of one kept prediction and the x before truncation (None: dropped):
    datasets/tusimple.py:63-71 (the h_samples over the original height, truncation, -2 where x < 0) on the
    TuSimple config's 320x800 input cut 160 rows from 1280x720 (clr_resnet18_tusimple.py:47-51)."""
    lane = official_lane(frac, start_y, length, ORI_H, CUT)
    if lane is None:
        return None
    values = lane_values(lane, np.asarray(H_SAMPLES) / ORI_H)
    written = (values * ORI_W).astype(int)
    written[values < 0] = -2
    return written.tolist(), values * ORI_W


def official_culane_points(frac: np.ndarray, start_y: np.float32, length: np.float32) -> np.ndarray:
    """The points the official CULane writer writes for one kept prediction (datasets/culane.py:96-112): the Lane
    at rows 270, 278, ..., 582 of the 1640x590 image (the CULane config cuts 270 rows: clr_resnet34_culane.py:47-51),
    kept where 0 <= x < 1 normalised, x times 1640, bottom first."""
    lane = official_lane(frac, start_y, length, CULANE_H, CULANE_CUT)
    if lane is None:
        return np.zeros((0, 2))
    ys = np.arange(270, 590, 8) / CULANE_H
    xs = lane_values(lane, ys)
    valid = (xs >= 0) & (xs < 1)
    return np.stack([xs[valid] * CULANE_W, ys[valid] * CULANE_H], axis=1)[::-1]


def _raw(case: dict) -> dict:
    """Our head's raw outputs for one image: the case's prediction (confident) and a rejected one."""
    lines = torch.zeros(1, 1, 2, 4)
    lines[0, 0, 0, 0] = float(case["start_y"])
    lines[0, 0, 0, 3] = float(case["length"])
    xs = torch.zeros(1, 1, 2, N_POINTS)
    xs[0, 0, 0] = torch.from_numpy(case["frac"]) * (IN_W - 1)  # our forward: the fraction x (W-1), float32
    logits = torch.tensor([[0.0, 3.0], [0.0, -3.0]]).reshape(1, 1, 2, 2)
    return {"cls_logits": logits, "lines": lines, "xs": xs}


@pytest.fixture(scope="module")
def detector():
    """What LaneDetector.decode_lanes reads: the head, its decode options and the crop (160 of 720 rows)."""
    head = CLRNetHead([64, 64, 64], [8, 16, 32], (IN_H, IN_W), num_priors=32, max_lanes=5, row_span="height")
    return SimpleNamespace(head=head, crop_top=0.2222222,
                           decode_kwargs={"conf_threshold": 0.4, "nms_threshold": 50.0, "nms_topk": 5,
                                          "lane_points": "official"})


def our_tusimple_lanes(detector, case: dict) -> list[list[int]]:
    """Our TuSimple file's lanes for one image: decode, map to the original image, keep as the records keep them,
    sample as the file does (the official experiment's row sampling: spline)."""
    lanes = LaneDetector.decode_lanes(detector, _raw(case), (IN_H, IN_W), [(ORI_H, ORI_W)])[0]
    record = prediction_fields(lanes, {"height": ORI_H, "width": ORI_W, "h_samples": H_SAMPLES}, 1.0, "spline")
    return tusimple_line({**record, "key": "clips/0530/0/20.jpg"})["lanes"]


def our_culane_points(detector, case: dict) -> list[np.ndarray]:
    """Our CULane file's lanes for one 1640x590 image (official_clrnet_culane: the crop of 270 rows, the spline read
    at model.culane_rows [270, 590, 8])."""
    culane = SimpleNamespace(**{**vars(detector), "crop_top": 0.4576271})
    lanes = LaneDetector.decode_lanes(culane, _raw(case), (IN_H, IN_W), [(CULANE_H, CULANE_W)])[0]
    record = prediction_fields(lanes, {"height": CULANE_H, "width": CULANE_W, "h_samples": [270.0]}, 1.0, "spline",
                               culane_rows=(270, 590, 8))
    points = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in record["pred_points"]]
    return culane_lanes(points, record["culane_rows"], "spline", CULANE_H, CULANE_W)


@pytest.mark.parametrize("name", list(CASES))
def test_official_culane_points(detector, name):
    """The same predictions in CULane's 1640x590 image: the official writer's points, row for row, x within
    0.001 px (the records keep 1e-4 px; the file writes 5 decimals)."""
    case = CASES[name]
    want = official_culane_points(case["frac"], case["start_y"], case["length"])
    got = our_culane_points(detector, case)
    if not len(want):
        assert got == []
        return
    (lane,) = got
    np.testing.assert_allclose(lane[:, 1], want[:, 1], atol=1e-9)  # the same rows
    np.testing.assert_allclose(lane[:, 0], want[:, 0], atol=1e-3)


@pytest.mark.parametrize("name", list(CASES))
def test_official_tusimple_rows(detector, name):
    case = CASES[name]
    official = official_tusimple_lane(case["frac"], case["start_y"], case["length"])
    got = our_tusimple_lanes(detector, case)
    if official is None:
        assert got == []
        return
    want, before_truncation = official
    written = before_truncation[np.asarray(want) >= 0]
    assert (np.abs(written - np.round(written)) > NEAR_INTEGER).all(), "a case too near a whole pixel"
    assert got == [want]


def test_the_cases_exercise_the_official_rules(detector):
    """The cases hold what they are named for, in the official file."""
    rows = {name: official_tusimple_lane(c["frac"], c["start_y"], c["length"])[0] for name, c in CASES.items()}
    assert max(rows["past the right edge"]) >= ORI_W  # x past the right edge written
    assert max(rows["starts right of the right edge"]) >= ORI_W
    dip = np.asarray(rows["dips out of the image and back"])
    inside = np.flatnonzero(dip >= 0)
    assert (dip[inside[0]:inside[-1]] == -2).any()  # a no-lane row inside the lane
    near_left = [x for x in rows["ends near the left edge"] if x >= 0]
    assert min(near_left) < 10
    # the half-even length: 10 rows from row 16 (16 .. 25), not 11
    extended = np.asarray(rows["extended down, half-even length"])
    assert extended[-1] >= 0  # extended down to the bottom sample
    assert rows["negative length"] is not None  # a negative length keeps all but the top rows (Python slice)


def test_inside_points_stay_the_default(detector):
    """Without lane_points the project's points (inside the image, border crossings) are decoded: no x past the
    right edge; an unknown value is refused naming the key."""
    head = detector.head
    assert "lane_points" in head.decode_options()
    lanes = head.decode(_raw(CASES["past the right edge"]))[0]
    assert lanes[0][:, 0].max() <= IN_W - 1
    with pytest.raises(ValueError, match="model.decode.lane_points"):
        head.decode(_raw(CASES["past the right edge"]), lane_points="all")


def test_official_experiment_sets_the_official_decoding():
    from tests.tasks.cli_helpers import composed

    cfg = composed(["experiment=official_clrnet_tusimple", "data.root=/data/tusimple"])
    assert cfg.model.decode.lane_points == "official"
    assert cfg.model.row_sampling == "spline"
    assert cfg.model.head.row_span == "height"
    assert round(cfg.data.crop_top * ORI_H) == CUT
