"""Longitudinal control in the closed loop: an adaptive cruise control (ACC) and an automatic emergency brake (AEB)
acting on a radar that sees objects only inside the ego lane as the policy perceives it.

task.longitudinal=acc (the default) drives with this; task.longitudinal=none keeps the constant speed of
task.vehicle.speed_mph (the paper's runs), traces and results unchanged.

**The radar** sees the simulator's object truth, the run's obstacles (closed_loop/collisions.py: the footprints a
standing illusion puts on the road, in road coordinates s, d), but only the parts inside the *corridor*: the ego
lane ahead as the policy perceives it, in the car's frame (x right, z forward, metres from the rear axle, where
the camera is). For a lane keeper (the detector and ground-truth policies) it is the tracker's centre line x(z)
+- half the tracked lane width + CORRIDOR margin (`corridor_margin_m`); for a policy without a tracked lane (the
VLM, or a lane keeper that has lost its lane) it is straight ahead along the car's heading, the default lane width
(task.lane_width_m) wide. The detector sees lanes, not objects: when its corridor misses the object's lane the
radar does not see the object, the car does not brake, and the collision that follows is a perception failure.
The radar measures the range from the car's front bumper to the nearest point of any object part inside the
corridor ahead of the rear axle (0 when that point is beside or behind the bumper), as far as the corridor is
known: the distance the tracked lane was seen (CentreLine.range_m), at most RADAR_RANGE_M (a lane seen only 15 m
ahead hides what stands beyond: the car brakes late). It sees road users (RADAR_KINDS: the traffic illusions'
vehicles, cyclists, pedestrians), not a guard rail: a rail runs along the road beside the lanes (at severity 5
its beam's face is 0.15 m inside the outermost line) and braking does not keep a car off it, steering does; a
real ACC's target selection drops such roadside structures too. The objects stand still, so the range closes at
the car's own speed.

**The controller** (`Longitudinal`, one per run), each control step, from the car's speed v and the radar range r:
* cruise: accelerate at `accel_mps2` back to the set speed (task.vehicle.speed_mph), never past it; at the set
  speed with nothing ahead the command is exactly 0 (the constant-speed car);
* ACC: with an object ahead, brake with the constant deceleration v^2 / (2 (r - standstill_m)) that stops the car
  `standstill_m` before it, at most `decel_mps2` (an ACC's own braking authority);
* AEB: when the time to collision r / v drops under `ttc_s` and the ACC's own braking can no longer stop the car
  before the object (v^2 / (2 r) > decel_mps2), or when r <= 0, brake at the vehicle's full deceleration
  (task.vehicle.max_decel_mps2) and keep braking until the car stands or the object leaves the corridor. (The
  time to collision alone would also fire at the end of the ACC's own planned stop: s0 / v + v / (2 a) falls to
  1.3 s at 3 m/s when the ACC brakes at 2.3 m/s^2.) No jerk limit: a command acts from the next control step (the
  control period is the only delay).
A stopped car stays stopped while the object is in its corridor (a standing object never moves away).

**Run-up** (`run_up_m`): in the paper's protocol the car starts 5-10 m before the illusion region at 45 mph, less
than any car needs to stop (v^2 / (2 * 8 m/s^2) = 25 m), so with longitudinal control the runs of the illusions
whose objects the radar sees (RADAR_KINDS) start this much earlier: the full-braking distance at the set speed
plus standstill_m and one control period of travel (29.3 m at 45 mph and 10 Hz). The car can then stop for any
object the radar sees from the start.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lanevil_train.closed_loop.collisions import FRONT_OVERHANG_M, Obstacle
from lanevil_train.closed_loop.tracker import CentreLine
from lanevil_train.rules import check_group, check_settings, number
from lanevil_train.sim import Scene
from lanevil_train.sim.sequence import z_at_arc_length
from lanevil_train.sim.vehicle import VehicleParams, VehicleState

MODES = ("acc", "none")  # task.longitudinal
RADAR_RANGE_M = 100.0  # objects further ahead are not seen (an automotive long-range radar sees 150-250 m)
RADAR_KINDS = frozenset(("vehicle", "bicycle", "pedestrian"))  # the road users it sees: not a guard rail
OUTLINE_STEP_M = 0.05  # an object's outline is sampled this finely (the nearest point inside the corridor lies on it)


@dataclass(frozen=True)
class AccSettings:
    """The ACC and emergency brake's settings (task.acc.*; see the module docstring): accel_mps2 and decel_mps2
    (m/s^2, the ACC's own limits), standstill_m (m, the gap it stops at), ttc_s (s, the AEB's time to collision),
    corridor_margin_m (m, added to half the tracked lane width on each side). lane_width_m (m, task.lane_width_m)
    is the corridor's width without a tracked lane."""

    # checked by the constructor and, by key (task.acc.<name>), by the config check before any work
    SETTINGS = {"accel_mps2": number(0, 5, low_open=True), "decel_mps2": number(0, 12, low_open=True),
                "standstill_m": number(0, 20), "ttc_s": number(0, 10, low_open=True),
                "corridor_margin_m": number(0, 1)}

    # ISO 15622 (ACC systems) limits an ACC's own acceleration to 2 m/s^2 and its deceleration to 3.5 m/s^2 (each
    # averaged over 2 s): the widely quoted figures; harder braking is the emergency brake's
    accel_mps2: float = 2.0
    decel_mps2: float = 3.5
    standstill_m: float = 2.0  # the gap a stopped ACC car keeps (2 m, the usual stop-and-go figure)
    # full braking from 45 mph (20.1 m/s) at 8 m/s^2 takes a time to collision of v / (2 a) = 1.26 s, so at 1.5 s
    # the car stops about 4.9 m short (one 0.1 s control period late: 2.9 m); emergency brakes act at a time to
    # collision of the order of 1-1.5 s. A higher speed needs more: ttc_s > v / (2 max_decel_mps2)
    ttc_s: float = 1.5
    # a car that keeps its lane (|deviation| < lane width / 2 - its half width) can touch only objects inside the
    # lane, so the lane would do; 0.2 m takes in an object whose box ends just beyond a lane line (a painted line
    # is 0.1-0.15 m wide) and the few centimetres a tracked lane is off
    corridor_margin_m: float = 0.2
    lane_width_m: float = 3.5

    def __post_init__(self) -> None:
        check_settings(self.SETTINGS, {name: getattr(self, name) for name in self.SETTINGS}, "task.acc")

    @classmethod
    def from_settings(cls, values: Mapping[str, Any], lane_width_m: float = 3.5,
                      prefix: str = "task.acc") -> AccSettings:
        """The settings of a mapping with the SETTINGS names (task.acc's; a key left out keeps its default); bad
        values and unknown keys named `prefix.<name>`."""
        check_group(cls.SETTINGS, values, prefix)
        return cls(**{name: float(value) for name, value in values.items()}, lane_width_m=float(lane_width_m))

    def run_up_m(self, vehicle: VehicleParams, period_s: float) -> float:
        """How much earlier a traffic illusion's run starts (m): the distance full braking needs from the set
        speed, v^2 / (2 max_decel), plus standstill_m and one control period of travel (module docstring)."""
        v = vehicle.speed_mps
        return v * v / (2.0 * vehicle.max_decel_mps2) + self.standstill_m + v * period_s


def straight_corridor(width_m: float) -> CentreLine:
    """The corridor of a policy without a tracked lane: straight ahead along the car's heading, width_m wide."""
    return CentreLine(offset_m=0.0, slope=0.0, curvature=0.0, width_m=width_m, range_m=RADAR_RANGE_M)


def _outline(obstacle: Obstacle, step_m: float = OUTLINE_STEP_M) -> np.ndarray:
    """(N, 2) points (s, d) around the obstacle's box, at most step_m apart."""
    corners = obstacle.corners()
    points = []
    for a, b in zip(corners, np.roll(corners, -1, axis=0)):
        n = max(1, math.ceil(float(np.hypot(*(b - a))) / step_m))
        points.append(a + np.linspace(0.0, 1.0, n, endpoint=False)[:, None] * (b - a))
    return np.concatenate(points)


def car_frame(points_sd: np.ndarray, state: VehicleState, posed: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Road points (N, 2) of (s, d) -> (x, z) in the car's frame (x right, z forward from the rear axle, m).

    `posed` is the scene seen from the car's pose (sequence.scene_at(reference, state.s, state.d,
    state.heading)): its world has the camera (rear axle) at the origin and z along the road's tangent there, so a
    point is at z = z_at_arc_length(s - state.s), x = offset_x(d, z), then turned by the car's heading."""
    road = posed.road
    z_world = z_at_arc_length(road, points_sd[:, 0] - state.s)
    x_world = road.offset_x(points_sd[:, 1], z_world)
    cos_h, sin_h = math.cos(state.heading), math.sin(state.heading)
    return x_world * cos_h - z_world * sin_h, x_world * sin_h + z_world * cos_h


def radar_range(state: VehicleState, posed: Scene, obstacles: Sequence[Obstacle], corridor: CentreLine,
                margin_m: float, wheelbase_m: float) -> float | None:
    """The range (m) from the car's front bumper to the nearest point of a road user (RADAR_KINDS) inside the
    corridor (its centre line x(z) +- corridor.width_m / 2 + margin_m, car frame) between the rear axle and as far
    as the corridor is known (z <= corridor.range_m, at most RADAR_RANGE_M); 0 when that point is level with or
    behind the bumper; None when no road user is in the corridor."""
    front = wheelbase_m + FRONT_OVERHANG_M
    half, far = corridor.width_m / 2.0 + margin_m, min(corridor.range_m, RADAR_RANGE_M)
    nearest = None
    for obstacle in obstacles:
        if obstacle.kind not in RADAR_KINDS:
            continue
        x, z = car_frame(_outline(obstacle), state, posed)
        seen = (z >= 0.0) & (z <= far) & (np.abs(x - corridor.x(z)) <= half)
        if np.any(seen):
            near = float(np.min(z[seen]))
            nearest = near if nearest is None else min(nearest, near)
    return None if nearest is None else max(nearest - front, 0.0)


@dataclass
class Longitudinal:
    """One run's ACC and emergency brake (module docstring): `command(speed, range)` -> (acceleration, info)."""

    settings: AccSettings
    vehicle: VehicleParams
    period_s: float
    braking: bool = field(default=False, init=False)  # the emergency brake is on (held until the car stands)

    def reset(self) -> None:
        self.braking = False

    def command(self, speed_mps: float, range_m: float | None) -> tuple[float, dict]:
        """The acceleration command (m/s^2, + faster, - braking) at speed `speed_mps` with the radar's range
        `range_m` (m, None: nothing in the corridor), and the trace's info: accel_mps2, radar_m, aeb."""
        accel = self._command(speed_mps, range_m)
        return accel, {"accel_mps2": round(accel, 6), "radar_m": None if range_m is None else round(range_m, 4),
                       "aeb": self.braking}

    def _command(self, v: float, r: float | None) -> float:
        acc = self.settings
        cruise = min(acc.accel_mps2, (self.vehicle.speed_mps - v) / self.period_s)  # to the set speed, not past
        if r is None or v <= 0.0:
            self.braking = False
            return cruise if r is None else min(cruise, 0.0)  # a stopped car waits while the object is there
        if self.braking or r <= 0.0 or (r < acc.ttc_s * v and v * v / (2.0 * r) > acc.decel_mps2):
            self.braking = True
            return -self.vehicle.max_decel_mps2
        room = r - acc.standstill_m
        need = v * v / (2.0 * room) if room > 0.0 else math.inf
        return min(cruise, -min(need, acc.decel_mps2))
