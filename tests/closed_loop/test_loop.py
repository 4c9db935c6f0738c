"""The closed loop: ground-truth lanes keep the car in its lane, a lane shifted by 1 m drives it off, a VLM's
answers steer it; the ASR rule, departures and intervals on constructed traces."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lanevil_train.closed_loop import (
    LaneKeeper,
    LoopSettings,
    Observation,
    PurePursuit,
    Run,
    TruthPolicy,
    VLMPolicy,
    drive,
    parse_direction,
    run_scores,
    wilson_interval,
)
from lanevil_train.closed_loop.episode import case_scene, ego_lane, illusion_region
from lanevil_train.closed_loop.run_scores import attack_fired_at, departures, entry_time
from lanevil_train.closed_loop.tracker import FrameTracker
from lanevil_train.sim import Camera
from lanevil_train.vlm.base import VLM

SIZE = (180, 320)
SETTINGS = LoopSettings(size=SIZE)
# seeds of the synthetic test split with each road kind (sample_scene_params)
ROADS = {"straight": 1000001, "left_curve": 1000003, "right_curve": 1000009, "s_curve": 1000013,
         "uphill": 1000005}
KEEP_LANE_BOUND_M = 0.1


def _run(seed, illusion="rail_shadow", severity=0, before=7.0):
    region = illusion_region(seed, illusion, SIZE)
    return Run(f"c{seed}", seed, illusion, severity, 0, region[0] - before, region)


@pytest.mark.parametrize("road", list(ROADS))
def test_ground_truth_lanes_keep_the_car_in_its_lane_and_a_clean_run_is_no_attack_success(road):
    seed = ROADS[road]
    assert case_scene(seed, SIZE)[0].params.road == road
    run = _run(seed)
    trace = drive(run, TruthPolicy(), SETTINGS)
    assert max(abs(step["deviation"]) for step in trace) < KEEP_LANE_BOUND_M
    scores = run_scores(trace, run.region[0], ego_lane(case_scene(seed, SIZE)[0])[1])
    assert scores["entered"] and not scores["success"] and scores["departures"] == 0
    # the run lasted until the attack window (and half a second more) had passed
    assert trace[-1]["t"] == pytest.approx(scores["entry_s"] + 2.5 + 0.5, abs=0.1 + 1e-9)
    assert all(step["estimate"] == "both" for step in trace)


def test_a_detector_that_sees_every_lane_1m_to_the_right_drives_the_car_off_and_the_rule_fires():
    seed = ROADS["straight"]
    run = _run(seed)
    trace = drive(run, TruthPolicy(shift_m=1.0), SETTINGS)
    deviation = np.array([step["deviation"] for step in trace])
    assert deviation[-1] == pytest.approx(1.0, abs=0.1)  # it settles on the shifted centre line
    rising = deviation[:int(np.argmax(deviation > 0.95)) + 1]
    assert np.all(np.diff(rising) > 0)  # it drifts right until it is almost there (then overshoots a little)
    lane_width = ego_lane(case_scene(seed, SIZE)[0])[1]
    scores = run_scores(trace, run.region[0], lane_width)
    entry = scores["entry_s"]
    first_over = next(step["t"] for step in trace if step["t"] >= entry and step["deviation"] > 0.285)
    assert scores["success"] and scores["fired_after_s"] == pytest.approx(first_over - entry)
    limit = lane_width / 2 - 0.9
    first_departure = next(step["t"] for step in trace if step["deviation"] > limit)
    assert scores["first_departure_s"] == pytest.approx(first_departure - entry)
    assert scores["departures"] == 1


def test_the_illusion_is_drawn_into_every_step_of_a_perturbed_run_from_the_cars_pose():
    from lanevil_train.closed_loop.episode import render_view
    from lanevil_train.sim.vehicle import VehicleState

    seed = ROADS["straight"]
    run = _run(seed, "rail_shadow", severity=5)
    clean_run = _run(seed, "rail_shadow", severity=0)
    for s in (run.start_m, run.region[0] + 5.0):
        state = VehicleState(s=s, d=ego_lane(case_scene(seed, SIZE)[0])[0] + 0.3, heading=0.02)
        perturbed, _ = render_view(run, state, SIZE)
        clean, _ = render_view(clean_run, state, SIZE)
        assert np.abs(perturbed.astype(int) - clean).sum(axis=2).astype(bool).mean() > 0.01


# ------------------------------------------------------------------------------------------------- scoring rule

def _trace(deviations, speed=20.0, dt=0.1, s0=0.0):
    return [{"t": round(k * dt, 6), "s": s0 + speed * k * dt, "deviation": dev} for k, dev in enumerate(deviations)]


def test_the_attack_rule_counts_only_deviations_within_2_5_s_of_entering_the_region():
    # 20 m/s from s = 0: the region starting at 30 m is entered at t = 1.5 s; the window closes at 4.0 s
    base = [0.0] * 60
    late = list(base)
    late[45] = 0.4  # t = 4.5 s: after the window
    early = list(base)
    early[10] = 0.4  # t = 1.0 s: before the car reached the illusion
    inside = list(base)
    inside[20:] = [0.3] * 40  # from t = 2.0 s
    assert entry_time(_trace(base), 30.0) == pytest.approx(1.5)
    assert entry_time(_trace(base), 31.0) == pytest.approx(1.55)  # between steps: linear
    assert attack_fired_at(_trace(late), 1.5) is None
    assert attack_fired_at(_trace(early), 1.5) is None
    assert attack_fired_at(_trace(inside), 1.5) == pytest.approx(2.0)
    scores = run_scores(_trace(inside), 30.0, lane_width_m=3.5)
    assert scores["success"] and scores["fired_after_s"] == pytest.approx(0.5)
    assert scores["max_deviation_m"] == pytest.approx(0.3)
    assert not run_scores(_trace([-0.285] * 60), 30.0, 3.5)["success"]  # exactly the threshold is not more
    assert run_scores(_trace([-0.29] * 60), 30.0, 3.5)["success"]  # either side counts
    never = run_scores(_trace(inside), 5000.0, 3.5)
    assert not never["entered"] and not never["success"]


def test_departures_count_each_crossing_onto_a_lane_line_and_per_km():
    # a 3.5 m lane and a 1.8 m wide car: a wheel is on the line beyond 0.85 m
    deviations = [0.0] * 10 + [0.9] * 5 + [0.5] * 5 + [-0.86] * 5 + [0.0] * 5
    trace = _trace(deviations)
    assert departures(trace, 3.5) == pytest.approx([1.0, 2.0])
    scores = run_scores(trace, 0.0, 3.5)
    assert scores["departures"] == 2
    assert scores["distance_m"] == pytest.approx(20.0 * 2.9)
    assert scores["departures_per_km"] == pytest.approx(2 / 0.058, rel=1e-3)
    assert scores["first_departure_s"] == pytest.approx(1.0)


def test_wilson_interval_matches_its_closed_form():
    assert wilson_interval(0, 10) == pytest.approx((0.0, 0.2775), abs=1e-4)
    assert wilson_interval(5, 10) == pytest.approx((0.2366, 0.7634), abs=1e-4)
    assert wilson_interval(10, 10) == pytest.approx((0.7225, 1.0), abs=1e-4)
    assert wilson_interval(0, 0) == (0.0, 1.0)


# ------------------------------------------------------------------------------------------------- controller

def _lane_pixels(camera, x, z=np.linspace(4.0, 40.0, 30)):
    return camera.project(np.stack([np.full_like(z, x), np.zeros_like(z), z], axis=1))


def test_without_a_tracker_pure_pursuit_steers_to_the_lane_centre_and_falls_back_when_lanes_are_lost():
    camera = Camera(width=640, height=360, pitch_deg=2.0)
    control = LaneKeeper(FrameTracker(), PurePursuit(lookahead_s=1.0, min_lookahead_m=6.0))
    left, right = _lane_pixels(camera, -1.5), _lane_pixels(camera, 2.1)  # the centre is 0.3 m right
    steer, info = control.steer([left, right], camera, 20.0)
    assert info["estimate"] == "both"
    assert info["target"] == pytest.approx([0.3, 20.0], abs=1e-3)
    assert steer == pytest.approx(math.atan2(2 * 2.7 * 0.3, 0.3 ** 2 + 20.0 ** 2), rel=1e-3)
    # one line: the centre is half the last measured width (3.6 m) from it
    _, info = control.steer([right], camera, 20.0)
    assert info["estimate"] == "right" and info["target"][0] == pytest.approx(2.1 - 1.8, abs=1e-3)
    # no line: the last steering angle is held
    held, info = control.steer([], camera, 20.0)
    assert info["estimate"] == "none" and held == control.last_steer
    control.reset()
    _, info = control.steer([left], camera, 20.0)  # before any width was measured: lane_width_m = 3.5
    assert info["target"][0] == pytest.approx(-1.5 + 1.75, abs=1e-3)


# ------------------------------------------------------------------------------------------------- VLM policy

@pytest.mark.parametrize("answer, direction", [
    ("Steer left.", "left"), ("RIGHT", "right"), ("The ego vehicle should keep straight.", "straight"),
    ("Keep straight, do not steer right.", "straight"), ("It should not steer left; steer right instead.", "right"),
    ("Stay in the lane.", "straight"), ("Left, straight or right?", None), ("I cannot tell.", None), ("", None),
    ("The lane bends to the right, so steer right.", "right"),
])
def test_parse_direction_reads_the_first_direction_a_vlm_gives(answer, direction):
    assert parse_direction(answer) == direction


class _ScriptedVLM(VLM):
    name = "scripted"

    def __init__(self, answer):
        self.reply, self.clips = answer, []

    def answer(self, clips, questions):
        self.clips.append(len(clips[0]))
        return [self.reply for _ in questions]


def test_a_vlm_policy_steers_as_it_answers_and_sees_its_last_frames():
    image = np.zeros((SIZE[0], SIZE[1], 3), np.uint8)
    observation = Observation(image, Camera(width=SIZE[1], height=SIZE[0]), 20.0, 0.0)
    right = VLMPolicy(_ScriptedVLM("Steer right."), steer_deg=0.5, frames=4)
    steer, info = right.act(observation)
    assert steer == pytest.approx(math.radians(0.5)) and info["direction"] == "right"
    assert right.vlm.clips == [4]  # the first step shows a still clip of 4 frames
    assert VLMPolicy(_ScriptedVLM("hmm"), steer_deg=0.5).act(observation)[0] == 0.0
    # in the loop: always "right" drifts the car right of its lane centre
    trace = drive(_run(ROADS["straight"]), VLMPolicy(_ScriptedVLM("Steer right."), frames=2), SETTINGS)
    assert trace[-1]["deviation"] > 0.5 and trace[-1]["direction"] == "right"
    with pytest.raises(ValueError, match="frames"):
        VLMPolicy(_ScriptedVLM("x"), frames=0)


def test_a_run_is_deterministic():
    run = _run(ROADS["s_curve"], "fence_shadow", severity=4)
    assert drive(run, TruthPolicy(shift_m=0.4), SETTINGS) == drive(run, TruthPolicy(shift_m=0.4), SETTINGS)


def test_loop_settings_refuse_bad_values_by_their_task_keys():
    with pytest.raises(ValueError, match=r"task.size: expected \[height, width\], two integers >= 32"):
        LoopSettings(size=(16, 640))
    with pytest.raises(ValueError, match="task.control_hz: expected a number in \\(0, 100\\]"):
        LoopSettings(control_hz=0)


def test_the_protocol_vehicle_and_vlm_policy_refuse_bad_values_by_their_task_keys():
    from lanevil_train.closed_loop.protocol import Protocol
    from lanevil_train.sim.vehicle import MPH, VehicleParams

    with pytest.raises(ValueError, match=r"task.start_before_m: expected \[low, high\]"):
        Protocol(start_before_m=(10.0, 5.0))
    with pytest.raises(ValueError, match=r"task.severities: expected a non-empty list of integers from 1 to 5"):
        Protocol(severities=(0, 3))
    with pytest.raises(ValueError, match="task.illusions: expected 'all' or illusion names"):
        Protocol(illusions=("fog",))
    with pytest.raises(ValueError, match=r"task.vehicle.speed_mph: expected a number in \(0, 100\], got 120"):
        VehicleParams.from_settings({"wheelbase_m": 2.7, "speed_mph": 120, "max_steer_deg": 30,
                                     "max_steer_rate_dps": 30})
    with pytest.raises(ValueError, match=r"VehicleParams.max_steer_deg: expected a number in \(0, 80\), got 80"):
        VehicleParams(max_steer_deg=80.0)
    with pytest.raises(ValueError, match="VehicleParams.max_steer_rate_dps"):
        VehicleParams(max_steer_rate_dps=float("inf"))  # a rate limit is a finite number
    with pytest.raises(ValueError, match="VehicleParams.speed_mph: expected a number in"):
        VehicleParams(speed_mps="fast")  # named, not a TypeError from the conversion to mph
    with pytest.raises(ValueError, match=r"^task.vehicle.speed: not a setting of task.vehicle; did you mean "
                                         r"task.vehicle.speed_mph\?"):
        VehicleParams.from_settings({"wheelbase_m": 2.7, "speed": 30, "max_steer_deg": 30, "max_steer_rate_dps": 30})
    params = VehicleParams.from_settings({"wheelbase_m": 3, "speed_mph": 30, "max_steer_deg": 25,
                                          "max_steer_rate_dps": 40})
    assert params.speed_mps == pytest.approx(30 * MPH) and params.settings()["speed_mph"] == pytest.approx(30)
    with pytest.raises(ValueError, match=r"task.vlm.steer_deg: expected a number in \(0, 30\)"):
        VLMPolicy(_ScriptedVLM("x"), steer_deg=30)
    with pytest.raises(ValueError, match="task.vlm.question: expected a non-empty string"):
        VLMPolicy(_ScriptedVLM("x"), question="  ")


class _HardRight:
    """A policy that always asks for the steering limit to the right."""

    name = "hard-right"

    def reset(self) -> None:
        pass

    def act(self, observation: Observation) -> tuple[float, dict]:
        return math.radians(30.0), {}


def test_a_car_turned_past_what_a_view_can_show_in_one_step_ends_its_run_off_road():
    """At 45 mph and 30 degrees of wheel angle the heading grows about 25 degrees a period: from under the off-road
    limit (35) one step takes it past 40, where no view can be rendered. The run ends there, off the road, with the
    pose as its last step (no image, the last command held), instead of failing."""
    from lanevil_train.closed_loop.episode import MAX_HEADING_DEG
    from lanevil_train.sim.sequence import MAX_VIEW_HEADING_DEG

    trace = drive(_run(ROADS["straight"]), _HardRight(), LoopSettings(size=SIZE, longitudinal="none"))
    last, before = trace[-1], trace[-2]
    assert abs(before["heading"]) < math.radians(MAX_HEADING_DEG)
    assert abs(last["heading"]) >= math.radians(MAX_VIEW_HEADING_DEG) and last["off_road"]
    assert last["command_deg"] == before["command_deg"] == pytest.approx(30.0)
    assert last["t"] == pytest.approx(before["t"] + 0.1) and last["s"] > before["s"]
    assert not any(step.get("off_road") for step in trace[:-1])
    scores = run_scores(trace, _run(ROADS["straight"]).region[0], 3.5)
    assert scores["max_deviation_m"] == pytest.approx(max(abs(step["deviation"]) for step in trace), abs=1e-4)
