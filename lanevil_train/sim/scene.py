"""Scene = camera + road geometry + seed-derived layout; the hand-off point for world-space illusions.

`build_scene(seed, params, width, height)` is deterministic. Illusions use `Scene.camera.project`,
`Scene.ground_hit` (pixels -> world ground points), `Scene.road_coords` / `Scene.road_point`
(world <-> road (s, d)), `Scene.road.height` and `Scene.sun_direction` to place 3D objects beside
the road and cast their shadows onto the ground.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lanevil_train.sim.camera import Camera
from lanevil_train.sim.params import SceneParams
from lanevil_train.sim.presets import MARKING_STRIPES, SCENE_KINDS, WEATHERS, marking_color
from lanevil_train.sim.road import Boundary, RoadGeometry

GT_MAX_DISTANCE = 100.0  # ground-truth lanes are annotated up to this forward distance (m)


def road_geometry(params: SceneParams, shoulder: float = 1.0) -> RoadGeometry:
    """The RoadGeometry described by params (camera at x = 0 inside the ego lane)."""
    n, w = params.num_lanes, params.lane_width
    offsets = [(i - n / 2.0) * w for i in range(n + 1)]
    boundaries = tuple(
        Boundary(d=float(offsets[i]), marking=mk, stripes=MARKING_STRIPES[mk], color=marking_color(mk))
        for i, mk in enumerate(params.resolved_markings))
    ego = params.resolved_ego_lane
    d_cam = offsets[ego] + w / 2.0 + params.lateral_offset
    k = j = grade = 0.0
    c = params.curvature
    if params.road == "left_curve":
        k = -c
    elif params.road == "right_curve":
        k = c
    elif params.road == "s_curve":
        k, j = c, -c / params.s_curve_flip
    elif params.road == "uphill":
        grade = params.grade
    elif params.road == "downhill":
        grade = -params.grade
    return RoadGeometry(x0=-d_cam, k=k, j=j, grade=grade, slope_start=params.slope_start,
                        slope_length=40.0, boundaries=boundaries, shoulder=shoulder)


@dataclass(frozen=True)
class Scene:
    """Everything geometric about one rendered scene."""

    seed: int
    params: SceneParams
    camera: Camera
    road: RoadGeometry
    dash_phase: float = 0.0  # dashes are painted where (s + travel - dash_phase) mod period < length

    @property
    def weather(self) -> dict:
        """The weather preset dict (colours, fog, sun...)."""
        return WEATHERS[self.params.weather]

    @property
    def kind(self) -> dict:
        """The scene-kind preset dict (verge, walls, lamps...)."""
        return SCENE_KINDS[self.params.scene_kind]

    @property
    def sun_direction(self) -> np.ndarray:
        """Unit world vector pointing towards the sun (below the horizon at night)."""
        el, az = (math.radians(v) for v in self.weather["sun"])
        return np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])

    def ground_hit(self, u, v) -> np.ndarray:
        """World points (..., 3) where pixel rays meet the road surface (NaN where they miss)."""
        return self.camera.ground_intersect(u, v, surface=self.road)

    def road_coords(self, x, z) -> tuple[np.ndarray, np.ndarray]:
        """World ground point (x, z) -> road coordinates (s along the centre line, d lateral, + right)."""
        return self.road.arc_length(np.asarray(z)), self.road.lateral(np.asarray(x), np.asarray(z))

    def road_point(self, s, d) -> np.ndarray:
        """Road coordinates (s, d) -> world points (..., 3) on the surface."""
        return self.road.world_point(d, self.road.z_at_arc_length(np.asarray(s, np.float64)))

    def lane_polyline(self, d: float, max_distance: float = GT_MAX_DISTANCE) -> np.ndarray:
        """Pixel polyline (N, 2), y descending, of the road line at lateral offset d: from where it
        enters the image up to max_distance, the image edge, or where a crest hides it."""
        cam, road = self.camera, self.road
        # dense in 1/z (uniform image rows on flat ground) and in z (far, nearly flat curves)
        z = np.union1d(1.0 / np.linspace(1.0 / 0.3, 1.0 / max_distance, 6000),
                       np.arange(5.0, max_distance, 0.1))
        pts = road.world_point(d, z)
        pix, depth = cam.project(pts, return_depth=True)
        u, v = pix[:, 0], pix[:, 1]
        # visibility: the ground hit along the ray towards each point must be that point
        rel = pts - cam.position
        with np.errstate(divide="ignore", invalid="ignore"):
            zhit = road.intersect(rel[:, 0] / rel[:, 2], rel[:, 1] / rel[:, 2], cam.height_m)
        visible = (depth > 1e-6) & (zhit >= z - 1e-3 * z - 1e-3)
        inside = visible & (u >= 0) & (u <= cam.width - 1) & (v >= 0) & (v <= cam.height - 1)
        if not inside.any():
            return np.zeros((0, 2))
        first = int(np.argmax(inside))
        run_end = first + (int(np.argmin(inside[first:])) if not inside[first:].all() else len(inside) - first)
        u, v = u[first:run_end], v[first:run_end]
        # keep the part where y keeps decreasing with distance
        dec = np.diff(v) < 0
        if not dec.all():
            stop = int(np.argmin(dec)) + 1
            u, v = u[:stop], v[:stop]
        if len(v) < 2:
            return np.zeros((0, 2))
        # one point every `step` pixels of path length (so also along nearly flat far curves)
        step = max(1.0, cam.height / 360.0)
        arc = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(u), np.diff(v)))])
        at = np.arange(0.0, arc[-1], step)
        at = np.append(at, arc[-1]) if arc[-1] - at[-1] > 1e-6 else at
        return np.stack([np.interp(at, arc, u), np.interp(at, arc, v)], axis=1)

    def lanes(self) -> tuple[list[np.ndarray], list[str], list[float]]:
        """GT lanes (painted boundaries only, left to right), their marking names and offsets d."""
        lanes, names, offs = [], [], []
        for b in self.road.boundaries:
            if b.marking == "none":
                continue
            line = self.lane_polyline(b.d)
            if len(line) >= 2:
                lanes.append(line)
                names.append(b.marking)
                offs.append(b.d)
        return lanes, names, offs


def build_scene(seed: int, params: SceneParams, width: int = 1280, height: int = 720) -> Scene:
    """The Scene of (seed, params) at this image size (the geometry does not depend on the size)."""
    for name, value in (("width", width), ("height", height)):
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value <= 0:
            raise ValueError(f"render size {name}: expected a positive integer, got {value!r}")
    if not isinstance(params, SceneParams):
        raise ValueError(f"params: expected a SceneParams or None, got {type(params).__name__}")
    lo, hi = SCENE_KINDS[params.scene_kind]["shoulder"]
    rng = np.random.default_rng([int(seed), 0x5140])
    shoulder = float(rng.uniform(lo, hi))
    dash_phase = float(rng.uniform(0.0, params.dash_length + params.dash_gap))
    camera = Camera(width=int(width), height=int(height), hfov_deg=params.hfov_deg,
                    height_m=params.camera_height, pitch_deg=params.pitch_deg, yaw_deg=params.yaw_deg)
    return Scene(seed=int(seed), params=params, camera=camera, road=road_geometry(params, shoulder),
                 dash_phase=dash_phase)
