"""sim.vehicle: the kinematic bicycle model against its closed forms, its limits, and bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lanevil_train.sim.road import RoadGeometry
from lanevil_train.sim.vehicle import MPH, VehicleParams, VehicleState, step

STRAIGHT = RoadGeometry()


def _drive(state, command, seconds, road=STRAIGHT, params=VehicleParams(), dt=0.1):
    states = [state]
    for _ in range(int(round(seconds / dt))):
        states.append(step(states[-1], command, dt, road, params))
    return states


@pytest.mark.parametrize("steer_deg", [4.0, -2.5])
def test_constant_steering_drives_a_circle_of_radius_wheelbase_over_tan_steer(steer_deg):
    params = VehicleParams(wheelbase_m=2.7, speed_mps=10.0)
    steer = math.radians(steer_deg)
    radius = 2.7 / math.tan(steer)  # signed: + turns right (towards + d)
    states = _drive(VehicleState(steer=steer), steer, 3.0, params=params)
    s = np.array([st.s for st in states])
    d = np.array([st.d for st in states])
    # on a straight road (s, d) are plane coordinates; the circle's centre is (0, radius)
    np.testing.assert_allclose(np.hypot(s, d - radius), abs(radius), atol=1e-6)
    # and the car has turned by the arc it drove over the radius
    assert states[-1].heading == pytest.approx(10.0 * 3.0 / radius, rel=1e-6)
    theta = 10.0 * 3.0 / radius
    assert (s[-1], d[-1]) == pytest.approx((radius * math.sin(theta), radius * (1 - math.cos(theta))), abs=1e-6)


def test_steering_to_the_road_curvature_follows_a_curve_on_its_centre_line():
    road = RoadGeometry(k=1 / 200.0)  # bends right, radius 200 m
    params = VehicleParams()
    steer = math.atan(params.wheelbase_m / 200.0)
    states = _drive(VehicleState(steer=steer), steer, 4.0, road=road, params=params)
    assert max(abs(st.d) for st in states) < 1e-6
    assert max(abs(st.heading) for st in states) < 1e-8
    assert states[-1].s == pytest.approx(4.0 * params.speed_mps, rel=1e-9)


def test_steering_is_limited_in_angle_and_rate():
    params = VehicleParams(max_steer_deg=10.0, max_steer_rate_dps=20.0)
    states = _drive(VehicleState(), math.radians(45.0), 1.0, params=params)
    steers = [math.degrees(st.steer) for st in states]
    assert steers[1] == pytest.approx(2.0)  # 20 deg/s for 0.1 s
    assert steers[5] == pytest.approx(10.0)  # then held at the 10 degree limit
    assert max(steers) == pytest.approx(10.0)


def test_default_speed_is_the_papers_45_mph():
    assert VehicleParams().speed_mps == pytest.approx(45 * MPH) == pytest.approx(20.1168)


def test_bad_vehicle_values_are_refused_naming_them():
    with pytest.raises(ValueError, match="wheelbase_m"):
        VehicleParams(wheelbase_m=0)
    with pytest.raises(ValueError, match="steering command"):
        step(VehicleState(), float("nan"), 0.1, STRAIGHT, VehicleParams())
    with pytest.raises(ValueError, match="dt"):
        step(VehicleState(), 0.0, 0.0, STRAIGHT, VehicleParams())
