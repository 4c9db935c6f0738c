"""Procedural road-scene renderer: pinhole camera over a road surface, painted lanes, weather.

Public API: render_scene(seed, params=None, width, height) -> {"image", "lanes", "meta"};
SceneParams / sample_scene_params; build_scene -> Scene (camera + road geometry, for illusions);
Camera; RoadGeometry; scene_at(scene, s0) -> the scene from s0 metres along the road (a driving
camera, sim/sequence.py) with FrameView / PoseCamera; preset names (ROAD_KINDS, MARKING_TYPES, WEATHER_NAMES,
SCENE_KIND_NAMES). Depends on numpy and opencv only.
"""

from lanevil_train.sim.camera import Camera
from lanevil_train.sim.params import SceneParams, sample_scene_params
from lanevil_train.sim.presets import MARKING_TYPES, ROAD_KINDS, SCENE_KIND_NAMES, WEATHER_NAMES
from lanevil_train.sim.render import render_scene, shade_scene
from lanevil_train.sim.road import RoadGeometry
from lanevil_train.sim.scene import GT_MAX_DISTANCE, Scene, build_scene, road_geometry
from lanevil_train.sim.sequence import FrameView, PoseCamera, road_at, scene_at

__all__ = [
    "Camera", "RoadGeometry", "Scene", "SceneParams", "build_scene", "road_geometry", "render_scene",
    "shade_scene", "sample_scene_params", "MARKING_TYPES", "ROAD_KINDS", "SCENE_KIND_NAMES",
    "WEATHER_NAMES", "GT_MAX_DISTANCE", "FrameView", "PoseCamera", "road_at", "scene_at",
]
