"""Where an illusion acts: the camera, the road in world metres, and the light.

Every illusion is rendered in world space from an IllusionContext, so it behaves the same on a
simulated scene (exact geometry, `context_from_scene`) and on a real photo (geometry recovered
from the annotated lanes, `recover.context_from_lanes`).

World frame (as in lanevil_train.sim): metres, x right, y up, z forward, camera above the origin.
Road frame: lateral offset d (+ right of the road centre line) and forward distance z;
`road.world_point(d, z)` gives the 3D point on the road surface, `road.lateral(x, z)` the inverse.

A frame of a clip (`context_for_frame`) keeps the reference view's road, so an illusion is laid out
exactly as in the reference image, and draws through a `PoseCamera` that maps reference-world points
into the moved camera: the illusion stays put on the road while the camera drives. Placement
decisions that look at the camera or the image (`placement`: draw.in_view, draw.RoadLight) read the
reference view, so every frame makes the same ones.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from lanevil_train.sim import Camera, RoadGeometry, Scene
from lanevil_train.sim.sequence import FrameView, PoseCamera


@dataclass(frozen=True)
class IllusionContext:
    """Geometry and lighting of one image, enough to place, shade and project 3D illusions."""

    camera: Camera                 # intrinsics, height, pitch, yaw; project() / ground_intersect()
    road: RoadGeometry             # centre line, vertical profile, lane boundaries (road.boundaries[i].d)
    lane_offsets: tuple[float, ...]  # d of each ground-truth lane, left to right (metres)
    sun_direction: np.ndarray      # unit world vector towards the sun (its y < 0: the sun is down)
    night: bool = False            # street lamps and headlights instead of the sun
    wet: float = 0.0               # 0 dry .. 1 soaked (reflections are strong on wet asphalt)
    view: FrameView | None = None  # a clip frame: the camera moved along the road (None: a single image)
    placement_image: np.ndarray | None = None  # the reference view's image, which placement reads

    @property
    def placement(self) -> "IllusionContext":
        """The context placement decisions read: the reference view of a clip frame, else this one."""
        if self.view is None:
            return self
        return replace(self, camera=self.view.reference.camera, view=None, placement_image=None)

    def frame(self) -> "IllusionContext":
        """The moved camera's own camera-centric context (for effects that follow the viewer), else this one."""
        if self.view is None:
            return self
        return replace(self, camera=self.view.camera, road=self.view.road, view=None, placement_image=None)

    @property
    def image_size(self) -> tuple[int, int]:
        """(H, W) of the image this context describes."""
        return self.camera.height, self.camera.width

    @property
    def lane_width(self) -> float:
        """Median spacing of adjacent ground-truth lanes (metres); 3.6 with fewer than two lanes."""
        d = np.sort(np.asarray(self.lane_offsets, dtype=np.float64))
        return float(np.median(np.diff(d))) if len(d) >= 2 else 3.6


def context_from_scene(scene: Scene) -> IllusionContext:
    """The exact context of a simulated scene (its own camera, road and weather)."""
    offsets = tuple(float(b.d) for b in scene.road.boundaries if b.marking != "none")
    weather = scene.weather
    return IllusionContext(camera=scene.camera, road=scene.road, lane_offsets=offsets,
                           sun_direction=scene.sun_direction, night=bool(weather["night"]),
                           wet=float(weather["wet"]))


def context_for_frame(reference: Scene, s0: float, reference_image: np.ndarray | None = None,
                      lateral: float | None = None, heading: float = 0.0) -> IllusionContext:
    """The context of the frame s0 metres along the road from `reference` (a car's pose: also its `lateral` offset
    and `heading`, as sim.scene_at): illusions are placed as in the reference view (whose clean image
    `reference_image` placement may read) and drawn from the pose."""
    view = FrameView.at(reference, s0, lateral, heading)
    return replace(context_from_scene(reference), camera=PoseCamera.of(view), view=view,
                   placement_image=reference_image)
