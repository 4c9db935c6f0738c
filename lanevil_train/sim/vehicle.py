"""The ego car: a kinematic bicycle model driving along a simulated road, in the road's own coordinates.

State (road / Frenet coordinates of the rear axle, which is also where the camera is mounted):
  s        arc length along the road's centre line from the reference pose (m)
  d        signed lateral offset from the centre line (m, + right), as RoadGeometry.lateral
  heading  angle between the car's axis and the road tangent (rad, + right)
  steer    front-wheel steering angle (rad, + right)
  speed    forward speed v (m/s, >= 0; None: the set speed VehicleParams.speed_mps)
Motion at speed v with road curvature kappa(s) = k + j s (RoadGeometry, + bends right):
  ds/dt = v cos(heading) / (1 - kappa d),  dd/dt = v sin(heading),
  dheading/dt = v tan(steer) / wheelbase - kappa ds/dt,  dv/dt = accel
(on a straight road this is the textbook bicycle x' = v cos(theta), y' = v sin(theta), theta' = v tan(steer) / L,
whose constant-steer path is a circle of radius L / tan(steer)). Each control step first moves the steering
towards the command (clipped to max_steer, at most max_steer_rate per second), then integrates with RK4 with the
acceleration command held over the step (clipped to the brakes' limit max_decel_mps2; the speed stops at 0, where
the car stands still for the rest of the step). An acceleration of 0 (the default) is the constant-speed car.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

from lanevil_train.rules import check_group, check_settings, is_number, number
from lanevil_train.sim.road import RoadGeometry

MPH = 0.44704  # metres per second in one mile per hour
INTEGRATION_STEP_S = 0.01  # RK4 sub-step


@dataclass(frozen=True)
class VehicleParams:
    """Wheelbase (m), set speed (m/s; 45 mph, the paper's OpenPilot runs, by default: the constant speed without
    longitudinal control, the cruise speed with it), steering limits (front-wheel angle in degrees and degrees per
    second) and the brakes' limit (m/s^2, the most deceleration any command gets)."""

    # The ranges, by the names task=closed_loop's config gives them (task.vehicle.*: the speed in mph, as the
    # paper's runs): checked by the constructor and, by key, by the config check before any work.
    SETTINGS = {"wheelbase_m": number(0.5, 10), "speed_mph": number(0, 100, low_open=True),
                "max_steer_deg": number(0, 80, low_open=True, high_open=True),
                "max_steer_rate_dps": number(0, low_open=True),
                # up to about 1.2 g, the grip of a good tyre on dry asphalt
                "max_decel_mps2": number(0, 12, low_open=True)}

    wheelbase_m: float = 2.7
    speed_mps: float = 45 * MPH
    max_steer_deg: float = 30.0
    max_steer_rate_dps: float = 30.0
    # about 0.8 g: a passenger car's full braking on dry asphalt, the order of what emergency-braking systems reach
    # in Euro NCAP's AEB tests (a widely quoted figure, not a measured one)
    max_decel_mps2: float = 8.0

    def __post_init__(self) -> None:
        check_settings(self.SETTINGS, self.settings(), "VehicleParams")

    def settings(self) -> dict[str, float]:
        """The parameters by their SETTINGS names (the speed in mph; a speed that is not a number as it is, for its
        rule to name)."""
        speed = self.speed_mps / MPH if is_number(self.speed_mps) else self.speed_mps
        return {"wheelbase_m": self.wheelbase_m, "speed_mph": speed,
                "max_steer_deg": self.max_steer_deg, "max_steer_rate_dps": self.max_steer_rate_dps,
                "max_decel_mps2": self.max_decel_mps2}

    @classmethod
    def from_settings(cls, values: Mapping[str, Any], prefix: str = "task.vehicle") -> VehicleParams:
        """The vehicle of a mapping with the SETTINGS names (task.vehicle's); bad values and unknown keys named
        `prefix.<name>`; max_decel_mps2 may be left out (its default)."""
        check_group(cls.SETTINGS, values, prefix)
        return cls(wheelbase_m=float(values["wheelbase_m"]), speed_mps=float(values["speed_mph"]) * MPH,
                   max_steer_deg=float(values["max_steer_deg"]),
                   max_steer_rate_dps=float(values["max_steer_rate_dps"]),
                   max_decel_mps2=float(values.get("max_decel_mps2", cls.max_decel_mps2)))


@dataclass(frozen=True)
class VehicleState:
    """Where the car is on the road, its speed (see the module docstring) and the time (s)."""

    s: float = 0.0
    d: float = 0.0
    heading: float = 0.0
    steer: float = 0.0
    t: float = 0.0
    speed: float | None = None  # m/s; None: the set speed of the VehicleParams it is stepped with

    def speed_mps(self, params: VehicleParams) -> float:
        """The car's speed (m/s): its own, or the set speed of `params` when it has none."""
        return params.speed_mps if self.speed is None else self.speed


def curvature_at(road: RoadGeometry, s: float) -> float:
    """The reference road's centre-line curvature s metres along it (1/m, + bends right)."""
    return road.k + road.j * s


def _derivatives(road: RoadGeometry, speed: float, wheelbase: float, steer: float, s: float, d: float,
                 heading: float) -> tuple[float, float, float]:
    kappa = curvature_at(road, s)
    ds = speed * math.cos(heading) / (1.0 - kappa * d)
    return ds, speed * math.sin(heading), speed * math.tan(steer) / wheelbase - kappa * ds


def step(state: VehicleState, command: float, dt: float, road: RoadGeometry, params: VehicleParams,
         accel: float = 0.0) -> VehicleState:
    """The state dt seconds later with steering command `command` (rad, + right) and acceleration command `accel`
    (m/s^2, + faster, - braking; clipped to -params.max_decel_mps2) held over the step. The speed never goes below
    0: a car braked to a stop stands still for the rest of the step. accel = 0 keeps the speed (exactly)."""
    if not math.isfinite(command):
        raise ValueError(f"steering command: expected a finite angle in radians, got {command!r}")
    if not math.isfinite(accel):
        raise ValueError(f"acceleration command: expected a finite acceleration in m/s^2, got {accel!r}")
    if not dt > 0:
        raise ValueError(f"dt: expected a positive time step in seconds, got {dt!r}")
    limit = math.radians(params.max_steer_deg)
    rate = math.radians(params.max_steer_rate_dps) * dt
    target = min(max(command, -limit), limit)
    steer = state.steer + min(max(target - state.steer, -rate), rate)
    v0, a = state.speed_mps(params), max(accel, -params.max_decel_mps2)
    moving = dt if v0 + a * dt >= 0.0 else v0 / -a  # how long it moves: until it stops, at most the step
    wheelbase = params.wheelbase_m
    s, d, heading = state.s, state.d, state.heading
    n = max(1, math.ceil(dt / INTEGRATION_STEP_S - 1e-9))
    h = moving / n
    for i in range(n):
        t0 = i * h
        v1, v2, v4 = v0 + a * t0, v0 + a * (t0 + h / 2), v0 + a * (t0 + h)  # the speed at RK4's stage times
        k1 = _derivatives(road, v1, wheelbase, steer, s, d, heading)
        k2 = _derivatives(road, v2, wheelbase, steer, s + h / 2 * k1[0], d + h / 2 * k1[1], heading + h / 2 * k1[2])
        k3 = _derivatives(road, v2, wheelbase, steer, s + h / 2 * k2[0], d + h / 2 * k2[1], heading + h / 2 * k2[2])
        k4 = _derivatives(road, v4, wheelbase, steer, s + h * k3[0], d + h * k3[1], heading + h * k3[2])
        s += h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        d += h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        heading += h / 6 * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2])
    speed = v0 + a * dt if moving == dt else 0.0
    return replace(state, s=s, d=d, heading=heading, steer=steer, t=state.t + dt, speed=max(speed, 0.0))
