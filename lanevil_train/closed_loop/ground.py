"""Detected lanes on the ground: pixels back-projected into the car's frame and fitted, and the ego lane's bounds.

The car knows its camera's mounting (intrinsics, height, pitch, yaw) but not the road: detected lane points
(image pixels) are back-projected onto a flat ground plane in the car's frame (x right, z forward, metres, origin
at the rear axle, where the camera sits). Each lane with at least MIN_POINTS points between MIN_RANGE_M and
`max_range_m` is fitted with x(z), a polynomial of degree <= 2.

The ego lane's bounds, from one frame alone, are the nearest lane left of the car and the nearest right of it,
measured NEAR_M ahead (`nearest_bounds`); a pair is a lane where their spacing is a plausible lane width
(MIN_WIDTH_M..MAX_WIDTH_M).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lanevil_train.sim import Camera

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

    def quadratic(self) -> tuple[float, float, float]:
        """(x at z = 0, slope dx/dz at 0, second derivative): the fit as x = a + b z + c/2 z^2."""
        a2, a1, a0 = np.concatenate([np.zeros(3 - len(self.coefficients)), self.coefficients])
        return float(a0), float(a1), float(2.0 * a2)


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


def nearest_bounds(lanes: list[GroundLane]) -> tuple[GroundLane | None, GroundLane | None]:
    """(the nearest lane left of the car, the nearest right of it) NEAR_M ahead; where both are seen but their
    spacing is no lane width, only the one nearer the car is kept."""
    near = [(float(lane.x(NEAR_M)), lane) for lane in lanes]
    left = max((item for item in near if item[0] < 0), key=lambda item: item[0], default=None)
    right = min((item for item in near if item[0] >= 0), key=lambda item: item[0], default=None)
    if left and right and not MIN_WIDTH_M <= right[0] - left[0] <= MAX_WIDTH_M:
        left, right = (left, None) if -left[0] <= right[0] else (None, right)
    return (left[1] if left else None), (right[1] if right else None)
