"""Longitudinal control: the bicycle model with an acceleration command against its closed forms, the ACC and the
emergency brake stopping for an object in the corridor and ignoring one beside it, the radar's corridor on a
curve, longitudinal=none leaving the drive as it was, and bad settings refused by their keys."""

from __future__ import annotations

import math

import pytest

from lanevil_train.closed_loop import LoopSettings, Run, TruthPolicy, VLMPolicy, drive
from lanevil_train.closed_loop import episode as episode_module
from lanevil_train.closed_loop.collisions import FRONT_OVERHANG_M, Obstacle, collision
from lanevil_train.closed_loop.episode import case_scene, ego_lane
from lanevil_train.closed_loop.longitudinal import AccSettings, Longitudinal, radar_range, straight_corridor
from lanevil_train.closed_loop.protocol import Protocol
from lanevil_train.closed_loop.run_scores import run_scores, twin_scores
from lanevil_train.closed_loop.tracker import CentreLine
from lanevil_train.sim.road import RoadGeometry
from lanevil_train.sim.sequence import scene_at
from lanevil_train.sim.vehicle import MPH, VehicleParams, VehicleState, step
from lanevil_train.vlm.base import VLM

SIZE = (64, 112)
STRAIGHT_SEED = 1000001  # a straight road: lanes 3.27 m wide, the ego lane centred on the road's centre line
RIGHT_CURVE_SEED = 1000009
V = 45 * MPH
FRONT_M = VehicleParams.wheelbase_m + FRONT_OVERHANG_M  # rear axle to front bumper
NEW_KEYS = {"speed_mps", "accel_mps2", "radar_m", "aeb", "stopped"}


def _clean_run(seed=STRAIGHT_SEED, start=0.0):
    """A clean run (nothing drawn) whose illusion region lies far beyond where the tests' objects stand."""
    return Run(f"c{seed}", seed, "rail_shadow", 0, 0, start, (60.0, 70.0))


def _in_lane(s_near, seed=STRAIGHT_SEED, right_of_centre=0.0):
    """A car-sized object (4.5 x 1.8 m) at s_near, centred right_of_centre metres right of the ego lane's centre."""
    centre = ego_lane(case_scene(seed, SIZE)[0])[0] + right_of_centre
    return Obstacle("vehicle", s_near, s_near + 4.5, centre - 0.9, centre + 0.9)


# ------------------------------------------------------------------------------------------ the bicycle model

def test_a_constant_deceleration_stops_the_car_in_v_squared_over_2a_and_it_stays_stopped():
    road, params = RoadGeometry(), VehicleParams()
    state = VehicleState(speed=V)
    for _ in range(70):  # 7 s at 4 m/s^2: it stops after 5.03 s, inside a step
        state = step(state, 0.0, 0.1, road, params, accel=-4.0)
        assert state.speed >= 0.0
    assert state.speed == 0.0
    assert state.s == pytest.approx(V * V / (2 * 4.0), abs=1e-9)
    # accelerating: s = v t + a t^2 / 2
    state = VehicleState(speed=10.0)
    for _ in range(20):
        state = step(state, 0.0, 0.1, road, params, accel=1.0)
    assert state.s == pytest.approx(10.0 * 2.0 + 2.0 ** 2 / 2, abs=1e-9) and state.speed == pytest.approx(12.0)
    # a harder command is held to the brakes' limit (8 m/s^2)
    state = VehicleState(speed=V)
    while state.speed > 0.0:
        state = step(state, 0.0, 0.1, road, params, accel=-100.0)
    assert state.s == pytest.approx(V * V / (2 * params.max_decel_mps2), abs=1e-9)


def test_no_acceleration_command_keeps_the_set_speed_exactly():
    road, params = RoadGeometry(k=0.004), VehicleParams()
    free, commanded = VehicleState(d=0.3), VehicleState(d=0.3, speed=params.speed_mps)
    for _ in range(30):
        free = step(free, 0.01, 0.1, road, params)
        commanded = step(commanded, 0.01, 0.1, road, params, accel=0.0)
    assert (free.s, free.d, free.heading) == (commanded.s, commanded.d, commanded.heading)
    assert free.speed == commanded.speed == params.speed_mps


# ------------------------------------------------------------------------------------ the ACC on its own

def test_the_acc_alone_stops_standstill_m_before_an_object_it_sees_far_enough_ahead():
    """An object 90 m ahead on a straight road, the true lane as the corridor: the ACC brakes with the constant
    deceleration that stops it standstill_m (2 m) short, 2.3 m/s^2, under its own limit: the emergency brake
    never acts."""
    scene = case_scene(STRAIGHT_SEED, SIZE)[0]
    centre, width = ego_lane(scene)
    box = _in_lane(FRONT_M + 90.0)
    lane = CentreLine(0.0, 0.0, 0.0, width, 120.0)  # seen 120 m ahead: the radar's 100 m limit the object's
    params, dt = VehicleParams(), 0.1
    control = Longitudinal(AccSettings(), params, dt)
    state, trace = VehicleState(d=centre, speed=V), []
    while state.t < 15.0:
        posed = scene_at(scene, state.s, state.d, state.heading)
        accel, info = control.command(state.speed, radar_range(state, posed, [box], lane, 0.2, params.wheelbase_m))
        trace.append({"t": state.t, "s": state.s, "d": state.d, "heading": state.heading, **info})
        state = step(state, 0.0, dt, scene.road, params, accel)
    assert trace[0]["radar_m"] == pytest.approx(90.0, abs=0.01)
    assert state.speed == 0.0 and not any(step_["aeb"] for step_ in trace)
    assert min(step_["accel_mps2"] for step_ in trace) == pytest.approx(-V * V / (2 * 88.0), abs=0.01)
    assert box.s_near - (state.s + FRONT_M) == pytest.approx(2.0, abs=0.01)
    assert not collision(trace, box)["collision"]


# ------------------------------------------------------------------------------------------- in the loop

def test_the_emergency_brake_stops_the_truth_policy_car_before_an_object_in_its_lane():
    """36 m ahead: more than the ACC's own 3.5 m/s^2 can stop in (58 m), so it brakes, then the emergency brake
    (time to collision under 1.5 s) brakes at 8 m/s^2 to a stop; the car's front never reaches the object."""
    box = _in_lane(40.0)
    trace = drive(_clean_run(), TruthPolicy(), LoopSettings(size=SIZE), [box])
    speeds = [step_["speed_mps"] for step_ in trace]
    assert speeds[0] == pytest.approx(V) and speeds[-1] == 0.0 and trace[-1]["stopped"]
    assert all(b <= a for a, b in zip(speeds, speeds[1:]))
    assert trace[0]["radar_m"] == pytest.approx(40.0 - FRONT_M, abs=0.01) and trace[0]["accel_mps2"] == -3.5
    assert any(step_["aeb"] and step_["accel_mps2"] == -8.0 for step_ in trace)
    gap = box.s_near - (trace[-1]["s"] + FRONT_M)
    assert 0.0 < gap < 10.0 and trace[-1]["radar_m"] == pytest.approx(gap, abs=0.01)
    assert not collision(trace, box)["collision"]
    # it stood still for a second before the run ended, far from the illusion region: never entered
    assert trace[-1]["t"] - next(step_["t"] for step_ in trace if step_["speed_mps"] == 0.0) == pytest.approx(1.0)
    scores = run_scores(trace, 60.0, 3.27)
    assert not scores["entered"] and not scores["success"] and scores["distance_m"] == pytest.approx(
        trace[-1]["s"] - trace[0]["s"], abs=1e-3)
    assert twin_scores(trace, trace, 60.0)["twin_max_deviation_m"] == 0.0  # a stopped twin (equal s) is read too
    # without longitudinal control the same car drives into it
    constant = drive(_clean_run(), TruthPolicy(), LoopSettings(size=SIZE, longitudinal="none"), [box])
    assert collision(constant, box)["collision"]


def test_an_object_in_the_next_lane_is_not_in_the_corridor_and_the_car_keeps_its_speed():
    width = ego_lane(case_scene(STRAIGHT_SEED, SIZE)[0])[1]
    beside = _in_lane(30.0, right_of_centre=width)  # fully in the lane to the right: 0.74 m beyond the line
    trace = drive(_clean_run(), TruthPolicy(), LoopSettings(size=SIZE), [beside])
    assert all(step_["speed_mps"] == V and step_["accel_mps2"] == 0.0 and step_["radar_m"] is None
               for step_ in trace)
    assert not collision(trace, beside)["collision"]
    assert trace == drive(_clean_run(), TruthPolicy(), LoopSettings(size=SIZE), [])  # as with nothing there


class _Straight(VLM):
    name = "straight"

    def answer(self, clips, questions):
        return ["Keep straight." for _ in questions]


def test_a_vlm_policy_brakes_for_an_object_straight_ahead():
    box = _in_lane(40.0)
    trace = drive(_clean_run(), VLMPolicy(_Straight(), frames=1), LoopSettings(size=SIZE), [box])
    assert trace[-1]["speed_mps"] == 0.0 and not collision(trace, box)["collision"]


# ------------------------------------------------------------------------------------------ the corridor

def test_the_radar_sees_only_the_corridor_and_follows_its_curve():
    scene = case_scene(RIGHT_CURVE_SEED, SIZE)[0]
    centre, width = ego_lane(scene)
    state = VehicleState(s=0.0, d=centre, speed=V)
    posed = scene_at(scene, state.s, state.d, state.heading)
    box = _in_lane(40.0, RIGHT_CURVE_SEED)  # in the ego lane, 40 m on along a right bend of radius 210 m
    k = posed.road.k  # the lane's curvature seen from the car (1/m, + right)
    lane = CentreLine(0.0, 0.0, k, width, 50.0)
    # 40 m of road is z = s - k^2 s^3 / 6 ahead (the simulator's road: arc length to third order), 0.24 m less
    assert radar_range(state, posed, [box], lane, 0.2, VehicleParams.wheelbase_m) == pytest.approx(
        40.0 - k * k * 40.0 ** 3 / 6 - FRONT_M, abs=0.01)
    # straight ahead the lane has bent 3.8 m to the right by then: a corridor that misses the curve misses it
    assert radar_range(state, posed, [box], straight_corridor(width), 0.2, VehicleParams.wheelbase_m) is None
    # a corridor one lane to the left (a detector locked onto the wrong lane) misses it too
    wrong = CentreLine(-width, 0.0, k, width, 50.0)
    assert radar_range(state, posed, [box], wrong, 0.2, VehicleParams.wheelbase_m) is None
    # a lane seen only 30 m ahead hides it (what lies beyond is not known to be in the lane)
    short = CentreLine(0.0, 0.0, k, width, 30.0)
    assert radar_range(state, posed, [box], short, 0.2, VehicleParams.wheelbase_m) is None
    # a guard rail is not a road user: even one in the corridor is not a target
    rail = Obstacle("guard_rail", box.s_near, box.s_far, box.d_left, box.d_right)
    assert radar_range(state, posed, [rail], lane, 0.2, VehicleParams.wheelbase_m) is None


# ------------------------------------------------------------------------------------------ longitudinal=none

def test_longitudinal_none_drives_as_before_and_acc_adds_only_its_keys(monkeypatch):
    box = _in_lane(40.0)
    none = LoopSettings(size=SIZE, longitudinal="none")
    trace = drive(_clean_run(), TruthPolicy(), none, [box])
    assert not NEW_KEYS & set().union(*trace)  # the trace keeps its keys
    old_step = episode_module.step
    monkeypatch.setattr(episode_module, "step", lambda state, command, dt, road, params, *rest:
                        old_step(state, command, dt, road, params))  # the constant-speed car, as it was
    assert drive(_clean_run(), TruthPolicy(), none, [box]) == trace
    monkeypatch.undo()
    # with acc and nothing in the corridor the car keeps the set speed: the same drive, with the ACC's keys
    acc = drive(_clean_run(), TruthPolicy(), LoopSettings(size=SIZE), [])
    assert [{k: v for k, v in step_.items() if k not in NEW_KEYS} for step_ in acc] == trace


def test_runs_with_road_users_start_earlier_by_the_braking_distance_only_with_acc():
    loop = LoopSettings(size=SIZE)
    run_up = loop.run_up_m()
    assert run_up == pytest.approx(V * V / 16.0 + 2.0 + V * 0.1) == pytest.approx(29.3, abs=0.05)
    assert LoopSettings(size=SIZE, longitudinal="none").run_up_m() == 0.0
    plan = dict(cases=1, first_seed=STRAIGHT_SEED, illusions=("rail_shadow", "guard_rail", "bicycle"),
                severities=(3,))
    before = {run.key: run.start_m for run in Protocol(**plan).runs(0, SIZE)}
    after = {run.key: run.start_m for run in Protocol(**plan, run_up_m=run_up).runs(0, SIZE)}
    for key, start in before.items():
        assert after[key] == pytest.approx(start - (run_up if "bicycle" in key else 0.0), abs=1e-4)


# ------------------------------------------------------------------------------------------ settings

def test_bad_longitudinal_settings_are_refused_by_their_task_keys():
    with pytest.raises(ValueError, match=r"task.acc.ttc_s: expected a number in \(0, 10\], got 0"):
        AccSettings(ttc_s=0.0)
    with pytest.raises(ValueError, match=r"^task.acc.ttc: not a setting of task.acc; did you mean task.acc.ttc_s\?"):
        AccSettings.from_settings({"ttc": 1.0})
    assert AccSettings.from_settings({"standstill_m": 3}, lane_width_m=3.7) == AccSettings(standstill_m=3.0,
                                                                                             lane_width_m=3.7)
    with pytest.raises(ValueError, match=r"task.vehicle.max_decel_mps2: expected a number in \(0, 12\], got 20"):
        VehicleParams.from_settings({"wheelbase_m": 2.7, "speed_mph": 45, "max_steer_deg": 30,
                                     "max_steer_rate_dps": 30, "max_decel_mps2": 20})
    with pytest.raises(ValueError, match="task.longitudinal: expected one of acc, none, got 'idm'"):
        LoopSettings(longitudinal="idm")
    with pytest.raises(ValueError, match=r"task.acc.decel_mps2: expected at most task.vehicle.max_decel_mps2 \(6"):
        LoopSettings(vehicle=VehicleParams(max_decel_mps2=6.0), acc=AccSettings(decel_mps2=7.0))
    with pytest.raises(ValueError, match="acceleration command: expected a finite"):
        step(VehicleState(), 0.0, 0.1, RoadGeometry(), VehicleParams(), accel=math.nan)
