"""Time-resolved closed-loop scores on constructed traces with hand-computed values: time to line crossing,
recovery, false lane lock (and the tracked boundaries mapped onto a curved road), and the report's columns."""

from __future__ import annotations

import math

import pytest

from lanevil_train.closed_loop import LoopSettings, Run, TruthPolicy, drive
from lanevil_train.closed_loop.episode import case_scene, ego_lane, illusion_region
from lanevil_train.closed_loop.time_scores import (
    TLC_CAP_S,
    FootprintEdges,
    boundaries_on_road,
    false_lane_lock,
    recovery_scores,
    time_scores,
    time_to_line_crossing,
    tlc_scores,
)
from lanevil_train.sim.road import Boundary, RoadGeometry

LANE_WIDTH_M = 3.5
MARGIN_M = LANE_WIDTH_M / 2 - 0.9  # the outer wheel's distance to the line when centred: 0.85 m
SPEED = 20.0
DT = 0.1
ROAD = RoadGeometry(boundaries=tuple(Boundary(d, "solid", (), "white") for d in (-1.75, 1.75)))


def _steps(n, s0=0.0, **columns):
    """n straight-road steps DT apart at SPEED from s0; columns: per-step lists (or constants) of other keys."""
    out = []
    for i in range(n):
        step = {"t": round(i * DT, 6), "s": s0 + i * DT * SPEED, "d": 0.0, "deviation": 0.0, "heading": 0.0}
        step.update({k: (v[i] if isinstance(v, list) else v) for k, v in columns.items()})
        out.append(step)
    return out


# --------------------------------------------------------------------------------------- time to line crossing
def test_tlc_is_the_outer_wheels_distance_to_the_line_over_the_lateral_speed_towards_it():
    assert time_to_line_crossing(0.25, 0.3, LANE_WIDTH_M) == pytest.approx((0.85 - 0.25) / 0.3)  # right line
    assert time_to_line_crossing(0.25, -0.3, LANE_WIDTH_M) == pytest.approx((0.85 + 0.25) / 0.3)  # left line
    assert time_to_line_crossing(0.25, 0.0, LANE_WIDTH_M) == math.inf  # parallel: never crosses
    assert time_to_line_crossing(-0.9, 0.3, LANE_WIDTH_M) == 0.0  # a wheel already on the left line


def test_tlc_on_a_car_drifting_right_at_constant_lateral_speed_and_its_minimum_over_the_window():
    heading = 0.01
    vy = SPEED * math.sin(heading)  # 0.19999667 m/s
    deviations = [0.1 + vy * i * DT for i in range(31)]  # 0.1 m right of centre at t = 0, drifting right for 3 s
    trace = _steps(31, deviation=deviations, d=deviations, heading=heading)
    entry = 0.5  # region from s = 10 m
    scores = tlc_scores(trace, entry, LANE_WIDTH_M, SPEED)
    # at entry (t = 0.5 s): (0.85 - 0.1 - 0.5 vy) / vy; the window's last step (t = 3.0 s): (0.85 - 0.1 - 3 vy) / vy
    assert scores["tlc_entry_s"] == pytest.approx((MARGIN_M - 0.1) / vy - 0.5, abs=1e-4)
    assert scores["tlc_min_s"] == pytest.approx((MARGIN_M - 0.1) / vy - 3.0, abs=1e-4)
    assert time_scores(trace, 10.0, LANE_WIDTH_M, SPEED, ROAD, FootprintEdges.from_points([], []))[
        "tlc_entry_s"] == scores["tlc_entry_s"]
    # a step's own speed (ACC) replaces the constant one: twice as fast, half the time
    fast = tlc_scores(_steps(31, deviation=deviations, heading=heading, speed_mps=2 * SPEED), entry, LANE_WIDTH_M,
                      SPEED)
    assert fast["tlc_entry_s"] == pytest.approx(((MARGIN_M - 0.1) / vy - 0.5) / 2, abs=1e-4)


def test_tlc_is_capped_when_parallel_and_none_without_an_entry():
    trace = _steps(31, deviation=0.2)
    assert tlc_scores(trace, 0.5, LANE_WIDTH_M, SPEED) == {"tlc_entry_s": TLC_CAP_S, "tlc_min_s": TLC_CAP_S}
    assert tlc_scores(trace, None, LANE_WIDTH_M, SPEED) == {"tlc_entry_s": None, "tlc_min_s": None}
    # moving back left from 0.2 m right: towards the left line, (0.85 + 0.2) / (20 sin 0.01) = 5.25 s
    left = tlc_scores(_steps(31, deviation=0.2, heading=-0.01), 0.5, LANE_WIDTH_M, SPEED)
    assert left["tlc_entry_s"] == pytest.approx(1.05 / (SPEED * math.sin(0.01)), abs=1e-4)


# --------------------------------------------------------------------------------------------------- recovery
def test_recovery_from_the_first_exceedance_to_the_first_step_back_within_the_threshold():
    trace = _steps(12, deviation=[0.0] * 5 + [0.3, 0.4, 0.3, 0.285, 0.1, 0.3, 0.0])
    # entry at s = 4 m (t = 0.2 s); out at t = 0.5 s (0.3 > 0.285); back at t = 0.8 s (0.285 is within)
    scores = time_scores(trace, 4.0, LANE_WIDTH_M, SPEED, ROAD, FootprintEdges.from_points([], []))
    assert scores["recovered"] is True and scores["recovery_s"] == pytest.approx(0.3)
    assert recovery_scores(_steps(8, deviation=[0.0] * 5 + [0.3, 0.5, 0.4]), 0.5) == {"recovered": False,
                                                                                        "recovery_s": None}
    assert recovery_scores(trace, None) == {"recovered": None, "recovery_s": None}  # never went out


# ------------------------------------------------------------------------------------------------ false lane lock
STRIPES = FootprintEdges.from_points(  # two painted stripes, d in [-1.0, -0.9] and [0.9, 1.0], s in [20, 60]
    [s / 10 for s in range(200, 601) for _ in range(4)],
    [d for _ in range(200, 601) for d in (-1.0, -0.9, 0.9, 1.0)])


def test_footprint_edges_are_the_sides_of_each_changed_band_near_the_arc_length():
    assert list(STRIPES.at(30.0)) == pytest.approx([-1.0, -0.9, 0.9, 1.0])
    assert list(STRIPES.at(60.9)) == pytest.approx([-1.0, -0.9, 0.9, 1.0])  # within EDGE_SPAN_M of the last cell
    assert len(STRIPES.at(61.5)) == 0
    merged = FootprintEdges.from_points([5.0] * 4, [0.0, 0.1, 0.3, 0.6])  # a 0.2 m gap joins, a 0.3 m one splits
    assert list(merged.at(5.0)) == pytest.approx([0.0, 0.3, 0.6, 0.6])


def test_false_lane_lock_counts_frames_near_an_illusion_edge_and_off_every_true_line():
    # the boundaries 10 m ahead of a car on the centre line (straight road: road d = car-frame x) at s_ahead =
    # 20 + 20 t; frames 2-4 and 6-7 right on the stripe (1.0: 0.75 m from the line at 1.75), frame 5 back on the
    # line (the lock broken by one frame), frame 8 at 1.3 (0.3 m from the edge but 0.45 m from the true line: no
    # lock), frame 9 lost (no boundaries), frame 11 the left boundary on the left stripe
    right = [1.75, 1.75, 1.0, 1.0, 1.0, 1.75, 1.0, 1.0, 1.3, None, 1.75, 1.75] + [1.75] * 18
    left = [-1.75] * 9 + [None, -1.75, -1.0] + [-1.75] * 18
    trace = _steps(30, s0=10.0, left_boundary_m=left, right_boundary_m=right)
    scores = false_lane_lock(trace, 0.0, ROAD, STRIPES)  # window [0, 2.5 s]: 26 frames
    assert scores == {"lock_frames": 6, "lock_longest_s": pytest.approx(0.3), "lock_share": round(6 / 26, 4)}
    clean = _steps(30, s0=10.0, left_boundary_m=-1.75, right_boundary_m=1.75)
    assert false_lane_lock(clean, 0.0, ROAD, STRIPES) == {"lock_frames": 0, "lock_longest_s": 0.0, "lock_share": 0.0}
    assert false_lane_lock(_steps(30), 0.0, ROAD, STRIPES)["lock_frames"] is None  # no tracker in the trace


def test_boundaries_on_road_follow_the_curve_and_the_heading():
    road = RoadGeometry(k=0.01)  # bends right: the centre line 10 m ahead is k z^2 / 2 = 0.5 m right
    step = {"t": 0.0, "s": 0.0, "d": 0.0, "heading": 0.0, "left_boundary_m": -1.25, "right_boundary_m": 2.25}
    s, left, right = boundaries_on_road(step, road)
    slope = math.sqrt(1 + (0.01 * 10) ** 2)  # lateral(): the perpendicular offset, to first order
    assert (left, right) == pytest.approx((-1.75 / slope, 1.75 / slope), abs=1e-9)
    assert s == pytest.approx(float(road.arc_length(10.0)))
    turned = {**step, "d": 0.5, "heading": 0.1, "left_boundary_m": 0.0, "right_boundary_m": 0.0}
    straight = boundaries_on_road(turned, RoadGeometry())  # on a straight road: d + x cos h + z sin h
    assert straight[1] == pytest.approx(0.5 + 10 * math.sin(0.1)) and straight[0] == pytest.approx(10 * math.cos(0.1))


def test_a_lane_keepers_tracked_boundaries_land_on_the_true_lines_of_a_curve():
    size, seed = (180, 320), 1000009  # a right curve of the synthetic test split
    region = illusion_region(seed, "rail_shadow", size)
    trace = drive(Run("c", seed, "rail_shadow", 0, 0, region[0] - 7.0, region), TruthPolicy(), LoopSettings(size))
    scene = case_scene(seed, size)[0]
    centre, width = ego_lane(scene)
    errors = [max(abs(left - (centre - width / 2)), abs(right - (centre + width / 2)))
              for _, left, right in (boundaries_on_road(step, scene.road) for step in trace)]
    assert max(errors) < 0.02  # the curve bends the lane ~0.2 m over 10 m: mapped through the road, not ignored
