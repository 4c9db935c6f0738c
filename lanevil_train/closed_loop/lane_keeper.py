"""Lane keeping from detected lanes: ground lanes -> a tracker -> a lateral controller, each control step.

`LaneKeeper.steer` back-projects one frame's detected lanes onto the ground (closed_loop/ground.py), gives them to
its tracker with the car's motion since the last frame (closed_loop/tracker.py: `kalman` or `none`), and steers
to the tracked centre line with its controller (closed_loop/lateral_controllers.py: `pure_pursuit`, `stanley`, `mpc`).
The motion is what the car knows of itself: its speed and its front-wheel angle give the distance and the yaw
(v tan(steer) / L per second). With no centre line (nothing seen, or the tracker lost the lane), the last steering
angle is held: the car keeps its arc, as a driver assist keeps its last plan for a moment.

The trace keeps where the tracker puts the ego lane's boundaries: `left_boundary_m` and `right_boundary_m`, the
tracked centre line's x(z) -/+ width / 2 at z = BOUNDARY_AHEAD_M ahead of the rear axle, in the car's frame (m,
+ right; None with no centre line). 10 m is where the default pure pursuit aims at 45 mph (0.5 s x 20.1 m/s):
where the tracked lane steers the car. closed_loop/time_scores.py maps them onto the road (its false lane lock).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lanevil_train.closed_loop.ground import MAX_WIDTH_M, MIN_WIDTH_M, ground_lanes
from lanevil_train.closed_loop.lateral_controllers import CONTROLLERS, Limits, PurePursuit
from lanevil_train.closed_loop.tracker import TRACKERS, CentreLine, FrameTracker, Motion
from lanevil_train.rules import check_group, check_settings, number
from lanevil_train.sim import Camera

__all__ = ["BOUNDARY_AHEAD_M", "KEEPER_SETTINGS", "LaneKeeper", "PurePursuit", "lane_keeper"]

BOUNDARY_AHEAD_M = 10.0  # where the trace records the tracked boundaries (m ahead of the rear axle)
KEEPER_SETTINGS = {"max_range_m": number(1), "lane_width_m": number(MIN_WIDTH_M, MAX_WIDTH_M)}


@dataclass
class LaneKeeper:
    """One frame's lanes -> the tracker -> the controller (see the module docstring)."""

    tracker: object = field(default_factory=FrameTracker)
    controller: object = field(default_factory=PurePursuit)
    max_range_m: float = 50.0
    period_s: float = 0.1
    last_steer: float = field(default=0.0, init=False)
    last_t: float | None = field(default=None, init=False)
    line: CentreLine | None = field(default=None, init=False)  # the last tracked centre line (the ACC's corridor)

    def __post_init__(self) -> None:
        check_settings({"max_range_m": KEEPER_SETTINGS["max_range_m"]}, {"max_range_m": self.max_range_m}, "task")

    def reset(self) -> None:
        """A new run: forget the track, the last steering angle and time."""
        self.tracker.reset()
        self.last_steer, self.last_t, self.line = 0.0, None, None

    def steer(self, lanes_px: list[np.ndarray], camera: Camera, speed_mps: float, t: float = 0.0,
              steer_rad: float = 0.0) -> tuple[float, dict]:
        """(front-wheel angle in rad, + right; info for the trace) from lanes detected in one image of `camera`,
        at time t (s) with the car's current front-wheel angle steer_rad."""
        dt = 0.0 if self.last_t is None else max(t - self.last_t, 0.0)
        self.last_t = t
        wheelbase = self.controller.limits.wheelbase_m
        motion = Motion(speed_mps * dt, speed_mps * math.tan(steer_rad) / wheelbase * dt, dt)
        lanes = ground_lanes(lanes_px, camera, self.max_range_m)
        line, info = self.tracker.update(lanes, motion)
        self.line = line
        info = {"lanes": len(lanes_px), "ground_lanes": len(lanes), **info, **tracked_boundaries(line)}
        if line is None:
            info["target"] = None
            return self.last_steer, info
        self.last_steer, control = self.controller.steer(line, speed_mps, self.period_s, steer_rad)
        info.update(control)
        info["centre_offset_m"] = round(float(line.offset_m), 4)
        return self.last_steer, info


def tracked_boundaries(line: CentreLine | None, ahead_m: float = BOUNDARY_AHEAD_M) -> dict:
    """{left_boundary_m, right_boundary_m}: the tracked lane's boundaries ahead_m ahead of the rear axle, in the car's
    frame (x(z) -/+ width / 2, m, + right), rounded to 0.1 mm; both None without a centre line."""
    if line is None:
        return {"left_boundary_m": None, "right_boundary_m": None}
    centre, half = float(line.x(ahead_m)), line.width_m / 2
    return {"left_boundary_m": round(centre - half, 4), "right_boundary_m": round(centre + half, 4)}


def lane_keeper(tracker: str = "kalman", controller: str = "pure_pursuit", limits: Limits = Limits(),
                max_range_m: float = 50.0, lane_width_m: float = 3.5, period_s: float = 0.1,
                settings: dict | None = None) -> LaneKeeper:
    """A LaneKeeper from names: `tracker` of TRACKERS, `controller` of CONTROLLERS; `settings` maps each name to
    its keyword arguments (e.g. {"kalman": {...}, "mpc": {...}}: task.kalman, task.mpc); `period_s`: the control
    period."""
    settings = settings or {}
    check_settings({"lane_width_m": KEEPER_SETTINGS["lane_width_m"]}, {"lane_width_m": lane_width_m}, "task")
    for kind, names, name in (("task.tracker", TRACKERS, tracker), ("task.controller", CONTROLLERS, controller)):
        if name not in names:
            raise ValueError(f"{kind}: expected one of {', '.join(names)}, got {name!r}")
    for name, owner in ((tracker, TRACKERS[tracker]), (controller, CONTROLLERS[controller])):
        check_group(getattr(owner, "SETTINGS", {}), settings.get(name) or {}, f"task.{name}")  # unknown keys too
    track = TRACKERS[tracker](lane_width_m=lane_width_m, **(settings.get(tracker) or {}))
    control = CONTROLLERS[controller](limits=limits, **(settings.get(controller) or {}))
    return LaneKeeper(track, control, max_range_m, period_s)
