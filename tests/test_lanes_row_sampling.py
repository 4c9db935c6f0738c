"""How decoded lanes are read at a dataset's rows (lanes.ROW_SAMPLINGS): the official spline writers' x, the
row-wise writers' -2 between points, and the prediction file and scores that read them."""

import json

import numpy as np
import pytest

from lanevil_train.evaluation.lane_records import lane_record
from lanevil_train.evaluation.prediction_files import prediction_fields, tusimple_line
from lanevil_train.lanes import INVALID_X, lanes_to_rows, sample_lane
from lanevil_train.models.detector import LaneDetector

H, W = 720, 1280
ROWS = np.arange(160, 720, 10, dtype=np.float64)


def cubic(ys):
    """A lane whose x is a cubic in y: the official interpolating spline (degree 3, scipy's not-a-knot ends)
    reproduces it exactly, so its values at the rows are known without a spline."""
    t = (ys - 400.0) / 100.0
    return 700.0 + 90.0 * t - 12.5 * t ** 2 + 3.25 * t ** 3


def test_spline_is_the_official_lane_truncated_and_valid_one_percent_past_its_ends():
    ys = np.linspace(300.0, 600.0, 13)
    lane = np.stack([cubic(ys), ys], 1)[::-1]
    xs = sample_lane(lane, ROWS, "spline", height=H)
    margin = 0.01 * H  # 7.2 px: rows 300 - 7.2 .. 600 + 7.2 are inside
    inside = (ROWS >= 300 - margin) & (ROWS <= 600 + margin)
    np.testing.assert_array_equal(xs[inside], np.trunc(cubic(ROWS[inside])))
    assert set(ROWS[inside]) == set(np.arange(300, 601, 10.0))  # 607.2 lets no row 610 in, 292.8 no 290
    assert np.all(xs[~inside] == INVALID_X)
    # a margin row is extrapolated: points at 303..603 make rows 300 and 610 (within 7.2 px) valid
    shifted = lane + np.array([0.0, 3.0])
    xs = sample_lane(shifted, ROWS, "spline", height=H)
    assert xs[ROWS == 300][0] == np.trunc(cubic(np.array([297.0])))[0]
    assert xs[ROWS == 610][0] == np.trunc(cubic(np.array([607.0])))[0]
    assert xs[ROWS == 290][0] == INVALID_X


def test_spline_keeps_x_past_the_right_edge_and_drops_x_left_of_zero():
    ys = np.linspace(200.0, 700.0, 11)
    right = np.stack([1000.5 + 1.23 * (ys - 200.0), ys], 1)  # passes x = 1280 at y 427
    xs = sample_lane(right, ROWS, "spline", height=H)
    assert xs[ROWS == 700][0] == 1615.0 and xs[ROWS == 440][0] == 1295.0  # 1615.5 and 1295.7, truncated
    left = np.stack([200.5 - 1.0 * (ys - 200.0), ys], 1)  # x < 0 below y 400
    xs = sample_lane(left, ROWS, "spline", height=H)
    assert xs[ROWS == 400][0] == 0.0 and np.all(xs[ROWS > 400] == INVALID_X)
    assert xs[ROWS == 390][0] == 10.0


def test_points_reads_only_rows_with_a_point_and_keeps_gaps():
    ys = np.array([710.0, 700.0, 690.0, 670.0, 660.0])  # no point at 680: a no-lane row inside the lane
    lane = np.stack([600.0 - (710 - ys) * 0.5, ys], 1)
    xs = sample_lane(lane, ROWS, "points")
    expect = np.full(len(ROWS), INVALID_X)
    for y, x in zip(ys, lane[:, 0]):
        expect[ROWS == y] = x
    np.testing.assert_array_equal(xs, expect)
    assert xs[ROWS == 680][0] == INVALID_X
    # linear reads across the gap
    assert sample_lane(lane, ROWS, "linear")[ROWS == 680][0] == pytest.approx(585.0)
    # a point 0.04 px off its row still counts; 0.2 px off does not
    nudged = lane + np.array([[0.0, 0.04], [0.0, 0.2], [0, 0], [0, 0], [0, 0]])
    xs = sample_lane(nudged, ROWS, "points")
    assert xs[ROWS == 710][0] == lane[0, 0] and xs[ROWS == 700][0] == INVALID_X


def test_an_unknown_sampling_and_a_spline_without_height_are_refused():
    lane = np.array([[10.0, 700.0], [20.0, 600.0]])
    with pytest.raises(ValueError, match="model.row_sampling='cubic': expected one of linear, spline, points"):
        lanes_to_rows([lane], ROWS, "cubic")
    with pytest.raises(ValueError, match="needs the image height"):
        sample_lane(lane, ROWS, "spline")


def test_the_prediction_file_and_the_scores_read_lanes_as_the_model_says():
    ys = np.linspace(300.0, 600.0, 13)
    lane = np.stack([cubic(ys), ys], 1)[::-1]
    meta = {"case_id": "c", "key": "clips/a/20.jpg", "h_samples": ROWS, "height": H, "width": W}
    record = {"key": meta["key"], **prediction_fields([lane], meta, 1.0, "spline")}
    line = tusimple_line(json.loads(json.dumps(record)))
    at = {int(y): x for y, x in zip(ROWS, line["lanes"][0])}
    assert at[500] == int(np.trunc(cubic(np.array([500.0])))[0]) and isinstance(at[500], int)
    assert at[610] == -2 and at[300] == int(cubic(np.array([300.0]))[0])
    # a ground truth equal to the spline's truncated values scores 1.0 under spline, as the official file would
    gt_rows = sample_lane(lane, ROWS, "spline", height=H)
    gt = np.stack([gt_rows[gt_rows >= 0], ROWS[gt_rows >= 0]], 1)[::-1]
    assert lane_record([lane], [gt], meta, row_sampling="spline")["accuracy"] == pytest.approx(1.0)
    linear = tusimple_line({"key": "k", **prediction_fields([lane], meta, 1.0)})
    at = {int(y): x for y, x in zip(ROWS, linear["lanes"][0])}
    assert at[600] == pytest.approx(cubic(np.array([600.0]))[0], abs=0.005) and at[610] == -2  # no margin


def test_a_detector_refuses_an_unknown_row_sampling():
    from torch import nn

    from lanevil_train.models.head import LaneHead

    with pytest.raises(ValueError, match="model.row_sampling='nearest'"):
        LaneDetector(nn.Identity(), LaneHead([8], [32], (32, 64)), row_sampling="nearest")


def test_culane_rows_read_a_spline_lane_untruncated_inside_the_image_as_the_official_culane_writers(tmp_path):
    from lanevil_train.evaluation.prediction_files import write_prediction_files
    from lanevil_train.lanes import culane_lanes
    from lanevil_train.results_log import ResultsLog

    height, width = 590, 1640
    ys = np.linspace(280.0, 589.0, 10)
    lane = np.stack([1500.25 + 0.9 * (ys - 280.0), ys], 1)[::-1]  # leaves the image (x = 1640) at y 435.8
    (read,) = culane_lanes([lane], [270, 590, 8], "spline", height, width)
    rows = np.arange(270, 590, 8.0)
    inside = (rows >= 280 - 5.9) & (1500.25 + 0.9 * (rows - 280.0) < width)  # margin 0.01 * 590
    np.testing.assert_allclose(read[:, 1], rows[inside][::-1])
    np.testing.assert_allclose(read[:, 0], 1500.25 + 0.9 * (read[:, 1] - 280.0), atol=1e-6)  # not truncated
    assert read[0, 1] == 430.0 and read[-1, 1] == 278.0  # bottom point first; 278 is inside the margin
    assert culane_lanes([lane], None, "spline", height, width)[0] is lane
    off = lane + np.array([width, 0.0])
    assert culane_lanes([off], [270, 590, 8], "spline", height, width) == []  # no point in the image: no line

    meta = {"case_id": "c", "key": "driver_1/a/00000.jpg", "h_samples": ROWS, "height": height, "width": width}
    record = {"model": "m", "dataset": "d", "key": meta["key"],
              **prediction_fields([lane], meta, 1.0, "spline", [270, 590, 8])}
    ResultsLog(tmp_path / "per_image.jsonl").append([record])
    files = write_prediction_files(tmp_path / "per_image.jsonl", tmp_path)
    text = (files["culane"] / "driver_1/a/00000.lines.txt").read_text().split()
    assert len(text) == 2 * len(read) and float(text[1]) == 430.0
    assert float(text[0]) == pytest.approx(read[0, 0], abs=1e-3)  # records keep points to 1e-6 px


def test_culane_rows_are_checked():
    from lanevil_train.lanes import check_culane_rows

    assert check_culane_rows([270, 590, 8]) == (270.0, 590.0, 8.0)
    for bad in ([270, 590], [590, 270, 8], [0, 590, 0], ["a", 1, 2]):
        with pytest.raises(ValueError, match=r"model.culane_rows=.*expected null .* \[start, stop, step\]"):
            check_culane_rows(bad)


def test_a_one_point_lane_is_written_under_points_and_left_out_under_linear():
    meta = {"case_id": "c", "key": "k", "h_samples": ROWS, "height": H, "width": W}
    one = [np.array([[321.5, 700.0]])]
    line = tusimple_line({"key": "k", **prediction_fields(one, meta, 1.0, "points")})
    assert len(line["lanes"]) == 1 and line["lanes"][0][ROWS.tolist().index(700.0)] == 321.5
    assert sum(x >= 0 for x in line["lanes"][0]) == 1
    assert tusimple_line({"key": "k", **prediction_fields(one, meta, 1.0)})["lanes"] == []
