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
from dataclasses import dataclass, replace

from lanevil_train.sim.road import RoadGeometry

MPH = 0.44704  # metres per second in one mile per hour
INTEGRATION_STEP_S = 0.01  # RK4 sub-step


def check_positive(label: str, value) -> float:
    """`value` as a float if it is a finite number > 0, else a ValueError naming `label`
    (e.g. VehicleParams.speed_mps)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{label}: expected a positive number, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class VehicleParams:
    """Wheelbase (m), constant speed (m/s; 45 mph, the paper's OpenPilot runs, by default), steering limits
    (front-wheel angle in degrees and degrees per second)."""

    wheelbase_m: float = 2.7
    speed_mps: float = 45 * MPH
    max_steer_deg: float = 30.0
    max_steer_rate_dps: float = 30.0

    def __post_init__(self) -> None:
        for name in ("wheelbase_m", "speed_mps", "max_steer_deg", "max_steer_rate_dps"):
            check_positive(f"VehicleParams.{name}", getattr(self, name))
        if self.max_steer_deg >= 80.0:
            raise ValueError(f"VehicleParams.max_steer_deg: expected under 80 degrees, got {self.max_steer_deg}")


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
