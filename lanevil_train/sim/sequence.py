"""A camera that drives along the road: the scene seen from a pose s0 metres further along the centre line.

The renderer is camera-centric (the camera sits at z = 0 and the road is a function of the forward
distance z), so a moved camera is rendered by re-expanding the road geometry at the new pose, in
the small-angle approximation the renderer itself uses:

* centre line: the curvature along the road is k + j s, so seen from arc length s0 it is
  k' = k + j s0, j' = j; the camera keeps its lateral offset in the lane (x0' = x0) and its heading
  follows the road (so a curve or an S-curve stays in front of it);
* vertical profile: flat until slope_start, a parabola of length L to the final grade g. The camera
  pitches with the road, so before the slope slope_start' = slope_start - s0; inside the transition
  (t0 = s0 - slope_start in (0, L)) slope_start' = 0, L' = L - t0, g' = g (1 - t0 / L) (the same
  parabola, grade / L); past it the road ahead is flat relative to the camera;
* dashes, textures and roadside dressing are anchored on the arc length, so travel' = travel + s0.

`FrameView` maps world points between the reference view (s0 = 0) and the moved one through road
coordinates (arc length s, lateral offset d, height above the road h): a point at (s, d, h) in the
reference view is at (s - s0, d, h) in the moved view. `PoseCamera` is a Camera that projects
reference-world points through that map, so anything laid out in the reference view (an illusion)
stays where it is on the road while the camera moves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from lanevil_train.sim.camera import Camera
from lanevil_train.sim.road import RoadGeometry
from lanevil_train.sim.scene import Scene

MAX_VIEW_HEADING_DEG = 40.0  # scene_at renders a car turned at most this far from the road


def road_at(road: RoadGeometry, s0: float) -> RoadGeometry:
    """The road geometry seen from the camera pose s0 metres further along the centre line."""
    if not math.isfinite(s0):
        raise ValueError(f"s0: expected a finite distance along the road in metres, got {s0!r}")
    k = road.k + road.j * s0
    if road.grade == 0.0:
        return replace(road, k=k)
    L = road.slope_length
    t0 = s0 - road.slope_start
    if t0 <= 0.0:
        return replace(road, k=k, slope_start=road.slope_start - s0)
    if t0 < L:
        return replace(road, k=k, slope_start=0.0, slope_length=L - t0, grade=road.grade * (1.0 - t0 / L))
    return replace(road, k=k, grade=0.0)


def scene_at(scene: Scene, s0: float, lateral: float | None = None, heading: float = 0.0) -> Scene:
    """The Scene rendered from s0 metres further along the road (negative: behind the reference).

    By default the camera keeps its lateral offset and looks along the road; a car's pose moves it to `lateral`
    (its offset d from the centre line, m, + right) and turns it by `heading` (rad, + right, from the road's
    tangent), a yaw added to the camera's mounting yaw.
    """
    s0 = float(s0)
    params = scene.params.replace(travel=scene.params.travel + s0)
    road = road_at(scene.road, s0)
    camera = scene.camera
    if lateral is not None:
        if not math.isfinite(lateral):
            raise ValueError(f"lateral: expected a finite offset from the centre line in metres, got {lateral!r}")
        road = replace(road, x0=-float(lateral))
    if heading:
        if not math.isfinite(heading) or abs(heading) >= math.radians(MAX_VIEW_HEADING_DEG):
            raise ValueError(f"heading: expected an angle to the road under {MAX_VIEW_HEADING_DEG:g} degrees (in "
                             f"radians), got {heading!r}")
        camera = replace(camera, yaw_deg=camera.yaw_deg + math.degrees(heading))
    return replace(scene, params=params, road=road, camera=camera)


def z_at_arc_length(road: RoadGeometry, s) -> np.ndarray:
    """Forward distance z where the centre line has run s metres (any sign; Newton on arc_length)."""
    s = np.asarray(s, dtype=np.float64)
    z = s.copy()
    if road.k == 0.0 and road.j == 0.0:
        return z
    for _ in range(4):
        dx = road.center_dx(z)
        z = z - (road.arc_length(z) - s) / (1.0 + 0.5 * dx * dx)
    return z


def _to_road(road: RoadGeometry, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points (..., 3) -> road coordinates (s, d, height above the surface)."""
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    return road.arc_length(z), road.lateral(x, z), y - road.height(z)


def _from_road(road: RoadGeometry, s, d, h) -> np.ndarray:
    """Road coordinates (s, d, h) -> world points (..., 3)."""
    z = z_at_arc_length(road, s)
    return np.stack([road.offset_x(d, z), road.height(z) + h, z], axis=-1)


@dataclass(frozen=True)
class FrameView:
    """The reference view (s0 = 0) and one moved along the road: maps world points between them."""

    reference: Scene
    current: Scene
    s0: float

    @classmethod
    def at(cls, reference: Scene, s0: float, lateral: float | None = None, heading: float = 0.0) -> "FrameView":
        """The view from s0 metres along the road of `reference` (from a car's pose: `scene_at`)."""
        return cls(reference=reference, current=scene_at(reference, s0, lateral, heading), s0=float(s0))

    @property
    def camera(self) -> Camera:
        """The moved camera (its own world frame)."""
        return self.current.camera

    @property
    def road(self) -> RoadGeometry:
        """The road seen from the moved camera."""
        return self.current.road

    def to_current(self, points) -> np.ndarray:
        """Reference-world points (..., 3) -> the same road points in the moved camera's world."""
        pts = np.asarray(points, dtype=np.float64)
        s, d, h = _to_road(self.reference.road, pts)
        return _from_road(self.current.road, s - self.s0, d, h)

    def to_reference(self, points) -> np.ndarray:
        """Moved-camera world points (..., 3) -> the same road points in the reference world."""
        pts = np.asarray(points, dtype=np.float64)
        s, d, h = _to_road(self.current.road, pts)
        return _from_road(self.reference.road, s + self.s0, d, h)


@dataclass(frozen=True)
class PoseCamera(Camera):
    """The moved camera, taking and giving points in the reference world (for illusions laid out there)."""

    view: FrameView | None = field(default=None, repr=False, compare=False)

    @classmethod
    def of(cls, view: FrameView) -> "PoseCamera":
        """The pose camera of a FrameView (same rig as the view's camera)."""
        cam = view.camera
        return cls(width=cam.width, height=cam.height, hfov_deg=cam.hfov_deg, height_m=cam.height_m,
                   pitch_deg=cam.pitch_deg, yaw_deg=cam.yaw_deg, view=view)

    def _view(self) -> FrameView:
        if self.view is None:
            raise ValueError("PoseCamera.view: expected a FrameView, got None (use PoseCamera.of(view))")
        return self.view

    @property
    def position(self) -> np.ndarray:
        """The moved camera's centre, in reference-world metres."""
        return self._view().to_reference(np.array([0.0, self.height_m, 0.0]))

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """Reference-world points (..., 3) -> the moved camera's frame (so project() works on them)."""
        pts = np.asarray(points, dtype=np.float64)
        if pts.shape[-1] != 3:
            raise ValueError(f"PoseCamera.to_camera: expected points of shape (..., 3), got {pts.shape}")
        return self._view().camera.to_camera(self._view().to_current(pts))

    def ground_intersect(self, u, v, surface=None) -> np.ndarray:
        """Pixels -> reference-world points on the road the moved camera sees (`surface` is ignored)."""
        view = self._view()
        return view.to_reference(view.camera.ground_intersect(u, v, surface=view.road))
