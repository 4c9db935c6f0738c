"""Collisions of the closed-loop car with the objects a standing illusion puts on the road.

Road coordinates throughout: s (m along the road's centre line), d (m lateral, + right), as sim.vehicle and the
traces. Both footprints are rectangles in (s, d) treated as a local Cartesian plane: this ignores the road's
curvature across the car and the object (under 1 cm at the simulator's curvatures and a 4.6 m car) and the
stretching of s away from the centre line (a factor 1 - kappa d, under 0.1 % there).

**Where standing illusions stand** (illusions/traffic.py, illusions/road_damage.py), at severity 3:
* `vehicle`: 2 cars or box trucks, 12-26 m ahead, each centred within 0.8 m of a lane line (the camera's own lane
  lines first, then the next): a car 1.8 m wide reaches 0.1-1.7 m into the lane beside that line, so about half
  of them block part of the ego lane. Heading within 0.06 rad of the road's.
* `bicycle`: 3 cyclists, 7-16 m ahead, within 0.4 m of a lane line; along the road or across it (1.7 m wheel to
  wheel either way).
* `pedestrian`: 4 people, 7-16 m ahead, within 0.4 m of a lane line, walking across the road (about 0.5 m wide
  and 0.3 m deep).
* `guard_rail`: a W-beam on posts beyond the road's outermost lane line on one side (0.9 m outside it at
  severity 3; both sides, 0.4 and 0.0 m outside, at severities 4 and 5), from 6 m ahead to 120 m: on the
  shoulder, not in a lane; a car reaches it only by leaving the road.

**The objects** (`obstacles`) are where the illusion itself put them: the same layout, drawn with the same seed
(traffic.layout, road_damage.rail_offsets), in the case's reference view, where the closed loop lays every
illusion out. A participant's footprint is the (s, d) box around every point of its parts (traffic
participant_points: body, wheels, riders), so a car turned 0.06 rad is 0.1-0.3 m wider than itself; a guard
rail's is its posts and beam (from the posts' outer face to the beam's road face) from where it starts to
RAIL_Z_FAR. Shadows are not objects.

**The car**: a rectangle around the rear axle (where a trace's s, d are): from REAR_OVERHANG_M behind it to
wheelbase + FRONT_OVERHANG_M ahead, 2 * HALF_CAR_WIDTH_M (1.8 m) wide, turned by the step's heading.
collision() tests it against each obstacle (separating-axis test) at every step and at points between steps
at most SUBSTEP_M apart (pose interpolated linearly), so a car cannot pass through a thin object between two
steps, and bisects the first contact to its time.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from lanevil_train.closed_loop.run_scores import HALF_CAR_WIDTH_M
from lanevil_train.illusions.context import context_from_scene
from lanevil_train.illusions.footprint import STANDING
from lanevil_train.illusions.parameters import level_params
from lanevil_train.illusions.road_damage import LEVELS, RAIL_Z_FAR, rail_offsets
from lanevil_train.illusions.traffic import layout, participant_points
from lanevil_train.sim import Scene
from lanevil_train.sim.vehicle import VehicleParams

WHEELBASE_M = VehicleParams.wheelbase_m  # the simulated car's default
REAR_OVERHANG_M = 1.0  # rear axle to rear bumper (a 4.6 m mid-size car with a 2.7 m wheelbase)
FRONT_OVERHANG_M = 0.9  # front axle to front bumper
SUBSTEP_M = 0.25  # most distance the car moves between two tested poses
_BISECT_STEPS = 30
RAIL_BEAM_OFFSET_M = 0.15  # the beam's face, on the road side of the posts (road_damage._draw_rail)
RAIL_POST_HALF_M = 0.08  # half a post's width


@dataclass(frozen=True)
class Obstacle:
    """An object's footprint on the road: s from s_near to s_far, d from d_left to d_right (m)."""

    kind: str
    s_near: float
    s_far: float
    d_left: float
    d_right: float

    def corners(self) -> np.ndarray:
        """(4, 2) corners (s, d), counter-clockwise in the (s, d) plane."""
        return np.array([[self.s_near, self.d_left], [self.s_far, self.d_left], [self.s_far, self.d_right],
                         [self.s_near, self.d_right]], np.float64)

    def as_dict(self) -> dict:
        return {"kind": self.kind, "s_near": round(self.s_near, 4), "s_far": round(self.s_far, 4),
                "d_left": round(self.d_left, 4), "d_right": round(self.d_right, 4)}


def obstacles(scene: Scene, illusion: str, severity: int | Mapping, seed: int) -> list[Obstacle]:
    """The objects a standing illusion at `severity` (or at a point of its parameters, a dict: task=search; drawn with
    `seed`) puts on the road of `scene`'s reference view, nearest first (by s_near); [] for an illusion that stands
    on nothing (see the module docstring) or severity 0."""
    if illusion not in STANDING or not severity:
        return []
    ctx = context_from_scene(scene)
    rng = np.random.default_rng(seed)  # as the illusion's registry entry seeds its renderer
    out = []
    if illusion == "guard_rail":
        z_start = level_params(LEVELS["guard_rail"], severity)["z_start_m"]
        near, far = (float(v) for v in scene.road.arc_length(np.array([z_start, RAIL_Z_FAR])))
        for d_rail, sign in rail_offsets(ctx, severity, rng):
            inner, outer = d_rail - sign * RAIL_BEAM_OFFSET_M, d_rail + sign * RAIL_POST_HALF_M
            out.append(Obstacle(illusion, near, far, min(inner, outer), max(inner, outer)))
    else:
        for participant in layout(illusion, ctx, severity, rng):
            points = participant_points(ctx, participant)
            s, d = scene.road_coords(points[:, 0], points[:, 2])
            out.append(Obstacle(illusion, float(np.min(s)), float(np.max(s)), float(np.min(d)), float(np.max(d))))
    return sorted(out, key=lambda o: (o.s_near, o.d_left))


def car_corners(s: float, d: float, heading: float, wheelbase_m: float = WHEELBASE_M,
                half_width_m: float = HALF_CAR_WIDTH_M) -> np.ndarray:
    """(4, 2) corners (s, d) of the car whose rear axle is at (s, d), turned by heading (rad, + right)."""
    fwd = np.array([math.cos(heading), math.sin(heading)])
    right = np.array([-math.sin(heading), math.cos(heading)])
    back, front = -REAR_OVERHANG_M, wheelbase_m + FRONT_OVERHANG_M
    centre = np.array([s, d], np.float64)
    return np.array([centre + a * fwd + b * right for a, b in
                     ((back, -half_width_m), (front, -half_width_m), (front, half_width_m), (back, half_width_m))])


def rectangles_overlap(a: np.ndarray, b: np.ndarray, eps: float = 1e-9) -> bool:
    """Whether two rectangles (each (4, 2) corners in order) overlap by more than eps (separating-axis test:
    they are apart iff their projections onto one of their edges' normals are)."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        for ex, ey in edges[:2]:  # a rectangle has two edge directions
            axis = np.array([-ey, ex])
            pa, pb = a @ axis, b @ axis
            if pa.max() <= pb.min() + eps * np.linalg.norm(axis) or pb.max() <= pa.min() + eps * np.linalg.norm(axis):
                return False
    return True


def collision(trace: Sequence[dict], obstacle: Obstacle | Sequence[Obstacle] | None, wheelbase_m: float = WHEELBASE_M,
              entry_s: float | None = None, substep_m: float = SUBSTEP_M) -> dict:
    """Whether the car of `trace` (steps with t, s, d, heading) touches the obstacle (or any of a list).

    collision (bool); collision_t: the first time its rectangle overlaps one (between steps, the pose is
    interpolated linearly at most substep_m apart and the contact bisected to 1e-6 of a step); time_to_collision_s:
    collision_t minus the run's start (trace[0]['t']); collision_after_entry_s: collision_t minus entry_s (the run's
    entry into the illusion region, run_scores.entry_time; negative when the car's front reaches the object before
    its rear axle enters the region; None without an entry); obstacle: the obstacle hit (as_dict), else None."""
    if not trace:
        raise ValueError("collision: an empty trace")
    targets = [] if obstacle is None else [obstacle] if isinstance(obstacle, Obstacle) else list(obstacle)
    boxes = [(o, o.corners()) for o in targets]

    def hit(pose):
        car = car_corners(pose[1], pose[2], pose[3], wheelbase_m)
        return next((o for o, box in boxes if rectangles_overlap(car, box)), None)

    poses = [(float(p["t"]), float(p["s"]), float(p["d"]), float(p.get("heading", 0.0))) for p in trace]
    found = _first_contact(poses, hit, substep_m) if boxes else None
    if found is None:
        return {"collision": False, "collision_t": None, "time_to_collision_s": None,
                "collision_after_entry_s": None, "obstacle": None}
    t, what = found
    return {"collision": True, "collision_t": round(t, 4), "time_to_collision_s": round(t - poses[0][0], 4),
            "collision_after_entry_s": None if entry_s is None else round(t - entry_s, 4),
            "obstacle": what.as_dict()}


def _first_contact(poses: list[tuple], hit, substep_m: float) -> tuple[float, Obstacle] | None:
    """(time, obstacle) of the first pose (t, s, d, heading) that `hit` finds touching one: each step, and poses
    between steps at most substep_m apart, the contact bisected between the last pose apart and the first not."""
    touched = hit(poses[0])
    if touched is not None:
        return poses[0][0], touched
    for before, after in zip(poses, poses[1:]):
        n = max(1, math.ceil(math.hypot(after[1] - before[1], after[2] - before[2]) / substep_m))
        lo = 0.0
        for k in range(1, n + 1):
            hi = k / n
            if hit(_lerp(before, after, hi)) is not None:
                for _ in range(_BISECT_STEPS):  # contact between lo (apart) and hi (overlapping)
                    mid = (lo + hi) / 2.0
                    lo, hi = (lo, mid) if hit(_lerp(before, after, mid)) is not None else (mid, hi)
                pose = _lerp(before, after, hi)
                return pose[0], hit(pose)
            lo = hi
    return None


def _lerp(a: tuple, b: tuple, f: float) -> tuple:
    return tuple(x + f * (y - x) for x, y in zip(a, b))
