"""benchmarks/lane_errors.py: a lane moved as a whole reads as an offset with nothing left after a line; a lane
bent reads as what is left; predictions squeezed towards the centre read as a slope under 1."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "lane_errors.py"
_spec = importlib.util.spec_from_file_location("lane_errors", SCRIPT)
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)

ROWS = list(range(300, 720, 10))


def _lane(x_of_y):
    return [[x_of_y(y), y] for y in ROWS]


def test_offsets_bends_and_the_pull_to_the_centre_are_told_apart():
    left, right = (lambda y: 600 - 0.8 * (y - 300)), (lambda y: 680 + 0.8 * (y - 300))
    shifted = {"gt_lanes": [_lane(left), _lane(right)],
               "pred_lanes": [_lane(lambda y: left(y) + 12), _lane(lambda y: right(y) - 12)]}
    summary = script.summary([shifted])
    assert summary["paired"] == 2 and summary["median |offset| px"] == pytest.approx(12)
    assert summary["median error after a line px"] == pytest.approx(0, abs=1e-9)

    bent = {"gt_lanes": [_lane(left)], "pred_lanes": [_lane(lambda y: left(y) + 8 * (1 if y % 20 else -1))]}
    assert script.summary([bent])["median error after a line px"] == pytest.approx(8, abs=0.5)

    squeezed = {"gt_lanes": [_lane(left), _lane(right)],
                "pred_lanes": [_lane(lambda y: 640 + 0.5 * (left(y) - 640)),
                               _lane(lambda y: 640 + 0.5 * (right(y) - 640))]}
    lines = script.centre_pull([squeezed], bands=((0, 10**6),))
    assert "predicted x = 0.500 x true + 320.0" in lines[0]


def test_a_lane_no_prediction_shares_three_rows_with_is_left_unpaired():
    record = {"gt_lanes": [_lane(lambda y: 100.0)], "pred_lanes": [[[100.0, 300], [100.0, 310]]]}
    assert script.summary([record])["paired"] == 0
