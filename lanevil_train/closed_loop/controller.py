"""Lane keeping from detected lanes: the ego lane's centre line in the car's frame, and pure pursuit on it.

The car knows its camera's mounting (intrinsics, height, pitch, yaw) but not the road: detected lane points
(image pixels) are back-projected onto a flat ground plane in the car's frame (x right, z forward, metres). Each
lane with at least MIN_POINTS points between MIN_RANGE_M and `max_range_m` is fitted with x(z), a polynomial of
degree <= 2. The ego lane is bounded by the nearest lane left of the car and the nearest right of it, measured at
NEAR_M ahead; its centre line is their mean where both are seen and their spacing is a plausible lane width
(MIN_WIDTH_M..MAX_WIDTH_M; that spacing is then remembered).

Fallback when a boundary is lost: one boundary seen, the centre line is that boundary shifted by half the last
plausible lane width (`lane_width_m` before any was measured); no lane seen, the last steering angle is held
(the car keeps its arc, as a driver assist keeps its last plan for a moment). Both are counted in the trace.

Pure pursuit (Coulter 1992): the target is the centre line's point `lookahead_s` seconds ahead at the car's speed
(at least `min_lookahead_m`, at most as far as the lanes used were seen), and the front-wheel angle is
atan(2 L x / (x^2 + z^2)) for a target at (x, z) from the rear axle: the arc through the target.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lanevil_train.sim import Camera
from lanevil_train.sim.vehicle import check_positive

MIN_POINTS = 3
MIN_RANGE_M = 1.0
NEAR_M = 6.0
MIN_WIDTH_M = 2.0
MAX_WIDTH_M = 5.0


@dataclass(frozen=True)
class GroundLane:
    """A detected lane on the ground in the car's frame: x(z) coefficients (numpy.polyval order) and its z span."""

    coefficients: np.ndarray
    z_near: float
    z_far: float

    def x(self, z) -> np.ndarray:
        """Lateral offset (m, + right) of the lane at forward distances z."""
        return np.polyval(self.coefficients, z)


def ground_lanes(lanes: list[np.ndarray], camera: Camera, max_range_m: float = 50.0) -> list[GroundLane]:
    """The detected pixel lanes (each (N, 2) x, y) as fitted ground lanes in the frame of `camera` (flat ground)."""
    out = []
    for lane in lanes:
        lane = np.asarray(lane, dtype=np.float64).reshape(-1, 2)
        points = camera.ground_intersect(lane[:, 0], lane[:, 1])
        x, z = points[:, 0], points[:, 2]
        keep = np.isfinite(x) & np.isfinite(z) & (z >= MIN_RANGE_M) & (z <= max_range_m)
        if keep.sum() < MIN_POINTS:
            continue
        x, z = x[keep], z[keep]
        if z.max() - z.min() < 1.0:
            continue
        degree = min(2, len(np.unique(np.round(z, 3))) - 1)
        out.append(GroundLane(np.polyfit(z, x, degree), float(z.min()), float(z.max())))
    return out


@dataclass
class PurePursuit:
    """Steering from detected lanes (see the module docstring); keeps the last lane width and steering angle."""

    wheelbase_m: float = 2.7
    lookahead_s: float = 0.5
    min_lookahead_m: float = 6.0
    max_range_m: float = 50.0
    lane_width_m: float = 3.5
    last_width_m: float | None = field(default=None, init=False)
    last_steer: float = field(default=0.0, init=False)

    def __post_init__(self) -> None:
        for name in ("wheelbase_m", "lookahead_s", "min_lookahead_m", "max_range_m", "lane_width_m"):
            check_positive(f"controller.{name}", getattr(self, name))

    def reset(self) -> None:
        """Forget the last lane width and steering angle (a new run)."""
        self.last_width_m = None
        self.last_steer = 0.0

    def centre_line(self, lanes: list[GroundLane]) -> tuple[object | None, float, str]:
        """(x(z) of the ego lane's centre, how far it is known (m), which estimate: both | left | right | none)."""
        near = [(float(lane.x(NEAR_M)), lane) for lane in lanes]
        left = max((item for item in near if item[0] < 0), key=lambda item: item[0], default=None)
        right = min((item for item in near if item[0] >= 0), key=lambda item: item[0], default=None)
        width = self.last_width_m or self.lane_width_m
        if left and right and MIN_WIDTH_M <= right[0] - left[0] <= MAX_WIDTH_M:
            self.last_width_m = right[0] - left[0]
            a, b = left[1], right[1]
            return (lambda z: (a.x(z) + b.x(z)) / 2.0), min(a.z_far, b.z_far), "both"
        if left and right:  # implausible spacing: keep the boundary nearer the car
            left, right = (left, None) if -left[0] <= right[0] else (None, right)
        if left:
            lane = left[1]
            return (lambda z: lane.x(z) + width / 2.0), lane.z_far, "left"
        if right:
            lane = right[1]
            return (lambda z: lane.x(z) - width / 2.0), lane.z_far, "right"
        return None, 0.0, "none"

    def steer(self, lanes_px: list[np.ndarray], camera: Camera, speed_mps: float) -> tuple[float, dict]:
        """(front-wheel angle in rad, + right; info for the trace) from lanes detected in one image of `camera`."""
        lanes = ground_lanes(lanes_px, camera, self.max_range_m)
        centre, known_m, estimate = self.centre_line(lanes)
        info = {"lanes": len(lanes_px), "ground_lanes": len(lanes), "estimate": estimate}
        if centre is None:
            info["target"] = None
            return self.last_steer, info
        z = max(self.min_lookahead_m, min(self.lookahead_s * speed_mps, known_m))
        x = float(centre(z))
        self.last_steer = math.atan2(2.0 * self.wheelbase_m * x, x * x + z * z)
        info["target"] = [round(x, 4), round(z, 3)]
        info["centre_offset_m"] = round(float(centre(0.0)), 4)
        return self.last_steer, info
