"""The ego car: a kinematic bicycle model driving along a simulated road, in the road's own coordinates.

State (road / Frenet coordinates of the rear axle, which is also where the camera is mounted):
  s        arc length along the road's centre line from the reference pose (m)
  d        signed lateral offset from the centre line (m, + right), as RoadGeometry.lateral
  heading  angle between the car's axis and the road tangent (rad, + right)
  steer    front-wheel steering angle (rad, + right)
Motion at constant speed v with road curvature kappa(s) = k + j s (RoadGeometry, + bends right):
  ds/dt = v cos(heading) / (1 - kappa d),  dd/dt = v sin(heading),
  dheading/dt = v tan(steer) / wheelbase - kappa ds/dt
(on a straight road this is the textbook bicycle x' = v cos(theta), y' = v sin(theta), theta' = v tan(steer) / L,
whose constant-steer path is a circle of radius L / tan(steer)). Each control step first moves the steering
towards the command (clipped to max_steer, at most max_steer_rate per second), then integrates with RK4.
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
    """Wheelbase (m), constant speed (m/s; 45 mph, the paper's OpenPilot runs, by default), steering limits
    (front-wheel angle in degrees and degrees per second)."""

    # The ranges, by the names task=closed_loop's config gives them (task.vehicle.*: the speed in mph, as the
    # paper's runs): checked by the constructor and, by key, by the config check before any work.
    SETTINGS = {"wheelbase_m": number(0.5, 10), "speed_mph": number(0, 100, low_open=True),
                "max_steer_deg": number(0, 80, low_open=True, high_open=True),
                "max_steer_rate_dps": number(0, low_open=True)}

    wheelbase_m: float = 2.7
    speed_mps: float = 45 * MPH
    max_steer_deg: float = 30.0
    max_steer_rate_dps: float = 30.0

    def __post_init__(self) -> None:
        check_settings(self.SETTINGS, self.settings(), "VehicleParams")

    def settings(self) -> dict[str, float]:
        """The parameters by their SETTINGS names (the speed in mph; a speed that is not a number as it is, for its
        rule to name)."""
        speed = self.speed_mps / MPH if is_number(self.speed_mps) else self.speed_mps
        return {"wheelbase_m": self.wheelbase_m, "speed_mph": speed,
                "max_steer_deg": self.max_steer_deg, "max_steer_rate_dps": self.max_steer_rate_dps}

    @classmethod
    def from_settings(cls, values: Mapping[str, Any], prefix: str = "task.vehicle") -> VehicleParams:
        """The vehicle of a mapping with the SETTINGS names (task.vehicle's); bad values and unknown keys named
        `prefix.<name>`."""
        check_group(cls.SETTINGS, values, prefix)
        return cls(wheelbase_m=float(values["wheelbase_m"]), speed_mps=float(values["speed_mph"]) * MPH,
                   max_steer_deg=float(values["max_steer_deg"]),
                   max_steer_rate_dps=float(values["max_steer_rate_dps"]))


@dataclass(frozen=True)
class VehicleState:
    """Where the car is on the road (see the module docstring) and the time (s)."""

    s: float = 0.0
    d: float = 0.0
    heading: float = 0.0
    steer: float = 0.0
    t: float = 0.0


def curvature_at(road: RoadGeometry, s: float) -> float:
    """The reference road's centre-line curvature s metres along it (1/m, + bends right)."""
    return road.k + road.j * s


def _derivatives(road: RoadGeometry, speed: float, wheelbase: float, steer: float, s: float, d: float,
                 heading: float) -> tuple[float, float, float]:
    kappa = curvature_at(road, s)
    ds = speed * math.cos(heading) / (1.0 - kappa * d)
    return ds, speed * math.sin(heading), speed * math.tan(steer) / wheelbase - kappa * ds


def step(state: VehicleState, command: float, dt: float, road: RoadGeometry, params: VehicleParams) -> VehicleState:
    """The state dt seconds later with steering command `command` (rad, + right) held over the step."""
    if not math.isfinite(command):
        raise ValueError(f"steering command: expected a finite angle in radians, got {command!r}")
    if not dt > 0:
        raise ValueError(f"dt: expected a positive time step in seconds, got {dt!r}")
    limit = math.radians(params.max_steer_deg)
    rate = math.radians(params.max_steer_rate_dps) * dt
    target = min(max(command, -limit), limit)
    steer = state.steer + min(max(target - state.steer, -rate), rate)
    v, wheelbase = params.speed_mps, params.wheelbase_m
    s, d, heading = state.s, state.d, state.heading
    n = max(1, math.ceil(dt / INTEGRATION_STEP_S - 1e-9))
    h = dt / n
    for _ in range(n):
        k1 = _derivatives(road, v, wheelbase, steer, s, d, heading)
        k2 = _derivatives(road, v, wheelbase, steer, s + h / 2 * k1[0], d + h / 2 * k1[1], heading + h / 2 * k1[2])
        k3 = _derivatives(road, v, wheelbase, steer, s + h / 2 * k2[0], d + h / 2 * k2[1], heading + h / 2 * k2[2])
        k4 = _derivatives(road, v, wheelbase, steer, s + h * k3[0], d + h * k3[1], heading + h * k3[2])
        s += h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        d += h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        heading += h / 6 * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2])
    return replace(state, s=s, d=d, heading=heading, steer=steer, t=state.t + dt)
