"""The lane tracker on constructed detections: no lag on a constant lane, a one-frame outlier gated, a lost lane
decays and then holds, the prediction moves the lane as the car's motion says; the controllers on true lanes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lanevil_train.closed_loop import LoopSettings, Run, TruthPolicy, drive, lane_keeper
from lanevil_train.closed_loop.episode import case_scene, illusion_region
from lanevil_train.closed_loop.ground import GroundLane
from lanevil_train.closed_loop.lane_keeper import tracked_boundaries
from lanevil_train.closed_loop.lateral_controllers import LinearMPC, PurePursuit, Stanley
from lanevil_train.closed_loop.tracker import CentreLine, KalmanLaneTracker, Motion

STEP = Motion(distance_m=2.0, yaw_rad=0.0, dt_s=0.1)  # 20 m/s at 10 Hz, straight


def _lane(x0, slope=0.0, curvature=0.0, near=3.0, far=40.0):
    return GroundLane(np.array([curvature / 2, slope, x0]), near, far)


def _track(tracker, frames):
    out = []
    for lanes, motion in frames:
        out.append(tracker.update(lanes, motion))
    return out


def test_a_constant_lane_is_estimated_from_the_first_frame_without_lag():
    tracker = KalmanLaneTracker()
    results = _track(tracker, [([_lane(-1.6), _lane(1.9)], STEP)] * 20)
    for line, info in results:
        assert info["estimate"] == "both"
        assert line.offset_m == pytest.approx(0.15, abs=0.01) and line.width_m == pytest.approx(3.5, abs=0.01)
        assert abs(line.slope) < 1e-3 and abs(line.curvature) < 1e-4
    assert tracker.rejected == 0 and results[-1][1]["confidence"] == 1.0


def test_a_curved_lane_keeps_its_curvature_and_the_car_moving_on_it_sees_it_shift():
    tracker = KalmanLaneTracker()
    for _ in range(5):  # a car standing still: five looks at the same curve settle curvature against its rate
        line, _ = tracker.update([_lane(-1.75, curvature=0.004), _lane(1.75, curvature=0.004)], Motion())
    assert line.curvature == pytest.approx(0.004, abs=2e-4) and abs(line.curvature_rate) < 2e-5
    # no detection: the prediction alone; the car drives 2 m straight along a lane curving right
    tracker.predict(STEP)
    line = tracker.centre_line()
    assert line.offset_m == pytest.approx(0.004 * 2.0 ** 2 / 2, abs=2e-3)
    assert line.slope == pytest.approx(0.004 * 2.0, abs=1e-3)


def test_the_prediction_moves_the_lane_as_the_cars_yaw_says():
    tracker = KalmanLaneTracker()
    tracker.update([_lane(-1.75), _lane(1.75)], Motion())
    before = tracker.centre_line()
    tracker.predict(Motion(distance_m=2.0, yaw_rad=0.02, dt_s=0.1))  # turning right: the lane swings left
    after = tracker.centre_line()
    assert after.offset_m - before.offset_m == pytest.approx(-0.02 * 2.0 / 2, abs=1e-9)
    assert after.slope - before.slope == pytest.approx(-0.02, abs=1e-9)
    assert after.width_m == pytest.approx(before.width_m)
    # its uncertainty grew
    assert np.all(np.diag(tracker.covariance)[:3] > 0)


def test_a_one_frame_outlier_is_gated_and_does_not_move_the_plan():
    keeper = lane_keeper("kalman", "pure_pursuit")
    tracker = keeper.tracker
    _track(tracker, [([_lane(-1.75), _lane(1.75)], STEP)] * 10)
    before = tracker.centre_line()
    # one frame: the left line seen 1 m into the lane (a shadow), the right one missed
    line, info = tracker.update([_lane(-0.75)], STEP)
    assert tracker.rejected == 1 and info["estimate"] == "predicted"
    assert line.offset_m == pytest.approx(before.offset_m, abs=0.005)
    steer_before, _ = keeper.controller.steer(before, 20.0, 0.1, 0.0)
    steer_after, _ = keeper.controller.steer(line, 20.0, 0.1, 0.0)
    assert steer_after == pytest.approx(steer_before, abs=1e-3)
    # a fake line beside the true one: the true one is taken (nearest to its prediction), the fake rejected; the
    # next lane's boundary (3.5 m out) is no rejection
    line, info = tracker.update([_lane(-0.9), _lane(-1.75), _lane(1.75), _lane(-5.25)], STEP)
    assert info["estimate"] == "both" and line.offset_m == pytest.approx(0.0, abs=0.01)
    assert tracker.rejected == 2


def test_a_lost_lane_decays_confidence_then_the_last_plan_is_held():
    keeper = lane_keeper("kalman", "pure_pursuit")
    camera = case_scene(1000001, (180, 320))[0].camera
    tracker = keeper.tracker
    _track(tracker, [([_lane(-1.5), _lane(2.0)], STEP)] * 5)
    confidences = []
    for _ in range(20):
        line, info = tracker.update([], STEP)
        confidences.append(info["confidence"])
        if line is None:
            break
    expected = [math.exp(-0.1 * k / 1.0) for k in range(1, len(confidences) + 1)]
    assert confidences[:-1] == pytest.approx(expected[:-1], abs=1e-4)
    lost_at = len(confidences)  # the first frame under min_confidence (0.2): exp(-0.1 k) < 0.2 from k = 17
    assert lost_at == 17 and line is None and info["estimate"] == "none"
    # the keeper holds its last steering angle while the lane is lost
    keeper.last_steer, keeper.last_t = 0.0123, 0.0
    held, info = keeper.steer([], camera, 20.0, 0.1, 0.0)
    assert held == 0.0123 and info["target"] is None
    assert info["left_boundary_m"] is None and info["right_boundary_m"] is None  # no tracked lane to record


def test_the_trace_records_the_tracked_boundaries_10m_ahead_in_the_cars_frame():
    line = CentreLine(offset_m=0.2, slope=0.01, curvature=0.002, width_m=3.5, range_m=40.0)
    # x(10) = 0.2 + 0.01 * 10 + 0.002 / 2 * 100 = 0.4; the boundaries -/+ 1.75 from it
    assert tracked_boundaries(line) == {"left_boundary_m": pytest.approx(-1.35),
                                        "right_boundary_m": pytest.approx(2.15)}
    assert tracked_boundaries(line, ahead_m=0.0) == {"left_boundary_m": pytest.approx(-1.55),
                                                     "right_boundary_m": pytest.approx(1.95)}


def test_the_controllers_steer_towards_the_centre_line():
    line = CentreLine(offset_m=0.3, slope=0.0, curvature=0.0, width_m=3.5, range_m=40.0)
    pursuit, info = PurePursuit(lookahead_s=1.0).steer(line, 20.0, 0.1, 0.0)
    assert info["target"] == pytest.approx([0.3, 20.0])
    assert pursuit == pytest.approx(math.atan2(2 * 2.7 * 0.3, 0.3 ** 2 + 20.0 ** 2))
    stanley, _ = Stanley(gain=1.0, softening_mps=1.0).steer(line, 20.0, 0.1, 0.0)
    assert stanley == pytest.approx(math.atan2(0.3, 21.0))
    mpc = LinearMPC()
    plan = mpc.plan(line, 20.0, 0.1, 0.0)
    assert plan[0] > 0  # right, towards the line
    # the rate limit binds: from a wheel angle of -5 degrees the first command moves at most 3 degrees
    plan = mpc.plan(line, 20.0, 0.1, math.radians(-5.0))
    assert plan[0] == pytest.approx(math.radians(-2.0), abs=1e-6)
    assert np.all(np.abs(np.diff(plan)) <= math.radians(3.0) + 1e-6)
    # on a curve with the car on it, the plan is the curve's own angle
    curve = CentreLine(0.0, 0.0, 0.004, 3.5, 40.0)
    assert mpc.plan(curve, 20.0, 0.1, math.atan(2.7 * 0.004))[0] == pytest.approx(math.atan(2.7 * 0.004), abs=2e-4)


SIZE = (180, 320)
ROADS = {"straight": 1000001, "left_curve": 1000003, "right_curve": 1000009, "s_curve": 1000013}


@pytest.mark.parametrize("controller", ["mpc", "stanley", "pure_pursuit"])
@pytest.mark.parametrize("road", list(ROADS))
def test_each_controller_on_the_tracked_true_lanes_keeps_the_car_within_2cm_5cm_on_an_s_curve(controller, road):
    seed = ROADS[road]
    region = illusion_region(seed, "rail_shadow", SIZE)
    run = Run(f"c{seed}", seed, "rail_shadow", 0, 0, region[0] - 7.0, region)
    trace = drive(run, TruthPolicy(lane_keeper("kalman", controller)), LoopSettings(size=SIZE))
    # the tracker's default noise is a detector's (benchmarks/tracker_noise.py): it trusts each frame's lanes
    # little, so on an S-curve its curvature lags (2-5 cm); on the other roads it stays within 2 cm
    bound = 0.05 if road == "s_curve" else 0.02
    assert max(abs(step["deviation"]) for step in trace) < bound
    assert all(step["estimate"] == "both" for step in trace) and trace[-1]["rejected"] == 0


def test_an_unknown_lane_keeper_setting_is_named_not_a_type_error():
    """A key the tracker or controller does not have (what Hydra's `+task.kalman.memry_s=0.3` lets in) is named by its
    dotted path with the nearest setting, before anything is built."""
    with pytest.raises(ValueError, match=r"^task\.kalman\.memry_s: not a setting of task\.kalman; did you mean "
                                         r"task\.kalman\.memory_s\? its settings: offset_sigma_m, "):
        lane_keeper("kalman", "pure_pursuit", settings={"kalman": {"memry_s": 0.3}})
    with pytest.raises(ValueError, match=r"^task\.mpc\.q_lat: not a setting of task\.mpc; did you mean "
                                         r"task\.mpc\.q_lateral\?"):
        lane_keeper("kalman", "mpc", settings={"mpc": {"q_lat": 2.0}})
    keeper = lane_keeper("kalman", "stanley", settings={"kalman": {"memory_s": 0.3}, "stanley": {"gain": 2.0}})
    assert keeper.tracker.memory_s == 0.3 and keeper.controller.gain == 2.0
