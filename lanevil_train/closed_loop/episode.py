"""One closed-loop run: the car starts before an illusion, a policy steers it from its camera, the trace is kept.

Each control step renders the camera view from the car's true pose (arc length s, lateral offset d, heading:
sim.scene_at), draws the run's illusion into it from that pose (laid out once in the case's reference view, so it
stays where it is on the road: illusions.context_for_frame), asks the policy for a steering angle, and moves the
car by the bicycle model (sim.vehicle) for one control period. A run ends `window_s + after_s` after the car
entered the illusion region, or when it has left the road (|deviation| > OFF_ROAD_M, or a heading of
MAX_HEADING_DEG to the road). A clean twin drives the same start with no illusion.

The illusion region of a case and illusion is its footprint on the road at REGION_SEVERITY in the reference view
(illusions.footprint): every severity and the clean twin share it, their start and their attack window.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from lanevil_train.closed_loop.collisions import Obstacle, obstacles
from lanevil_train.closed_loop.policies import Observation, Policy
from lanevil_train.illusions.context import context_for_frame, context_from_scene
from lanevil_train.illusions.footprint import STANDING, footprint
from lanevil_train.illusions.registry import get_illusion
from lanevil_train.rules import check_settings, int_pair, number
from lanevil_train.sim import Scene, build_scene, sample_scene_params, shade_scene
from lanevil_train.sim.sequence import scene_at
from lanevil_train.sim.vehicle import VehicleParams, VehicleState, step
from lanevil_train.taxonomy import ILLUSION_CATEGORY

REGION_SEVERITY = 3
OFF_ROAD_M = 3.0
MAX_HEADING_DEG = 35.0


@dataclass(frozen=True)
class Run:
    """One run: a case (scene seed), the illusion it is about and its severity (0: the clean twin), the repeat,
    where the car starts and the illusion region (arc lengths from the reference view, m)."""

    case_id: str
    seed: int
    illusion: str
    severity: int
    repeat: int
    start_m: float
    region: tuple[float, float]

    @property
    def key(self) -> str:
        """Unique within a model's runs: case/illusion/severity/repeat."""
        return f"{self.case_id}/{self.illusion}/{self.severity}/{self.repeat}"

    @property
    def category(self) -> str:
        return ILLUSION_CATEGORY[self.illusion]

    def as_dict(self) -> dict:
        return {"run": self.key, "case_id": self.case_id, "seed": self.seed, "illusion": self.illusion,
                "category": self.category, "severity": self.severity, "perturbed": self.severity > 0,
                "repeat": self.repeat, "start_m": round(self.start_m, 4),
                "region_m": [round(v, 4) for v in self.region]}


@dataclass(frozen=True)
class LoopSettings:
    """Image size (H, W), control rate (Hz), attack window and what is driven after it (s), the vehicle."""

    SETTINGS = {"size": int_pair(32), "control_hz": number(0, 100, low_open=True),
                "window_s": number(0, low_open=True), "after_s": number(0)}  # task.<name> of task=closed_loop

    size: tuple[int, int] = (360, 640)
    control_hz: float = 10.0
    window_s: float = 2.5
    after_s: float = 0.5
    vehicle: VehicleParams = field(default_factory=VehicleParams)

    def __post_init__(self) -> None:
        check_settings(self.SETTINGS, {name: getattr(self, name) for name in self.SETTINGS}, "task")


@lru_cache(maxsize=8)
def case_scene(seed: int, size: tuple[int, int]) -> tuple[Scene, np.ndarray]:
    """The case's scene from its reference pose and its clean reference image (where illusions are laid out)."""
    scene = build_scene(int(seed), sample_scene_params(int(seed)), size[1], size[0])
    return scene, shade_scene(scene)


def ego_lane(scene: Scene) -> tuple[float, float]:
    """(lateral offset of the ego lane's centre from the road's centre line, lane width), metres."""
    bounds = [b.d for b in scene.road.boundaries]
    ego = scene.params.resolved_ego_lane
    return (bounds[ego] + bounds[ego + 1]) / 2.0, bounds[ego + 1] - bounds[ego]


def illusion_region(seed: int, illusion: str, size: tuple[int, int]) -> tuple[float, float]:
    """(near, far) arc lengths (m) of the illusion's footprint on the road of the case's reference view."""
    scene, clean = case_scene(seed, size)
    perturbed = get_illusion(illusion)(clean, context_from_scene(scene), REGION_SEVERITY, seed)
    area = footprint(scene, clean, perturbed, standing=illusion in STANDING)
    return area.near_m, area.far_m


@lru_cache(maxsize=64)
def run_obstacles(seed: int, illusion: str, severity: int, size: tuple[int, int]) -> tuple[Obstacle, ...]:
    """The objects a standing illusion puts on the road of the case at this severity (closed_loop/collisions.py);
    none for a clean twin or an illusion that stands on nothing."""
    return tuple(obstacles(case_scene(seed, size)[0], illusion, severity, seed))


def render_view(run: Run, state: VehicleState, size: tuple[int, int]) -> tuple[np.ndarray, Scene]:
    """The camera image at the car's pose, with the run's illusion (none for a clean twin), and the posed scene."""
    scene, reference = case_scene(run.seed, size)
    posed = scene_at(scene, state.s, state.d, state.heading)
    image = shade_scene(posed)
    if run.severity:
        context = context_for_frame(scene, state.s, reference, state.d, state.heading)
        image = get_illusion(run.illusion)(image, context, run.severity, run.seed)
    return image, posed


def drive(run: Run, policy: Policy, settings: LoopSettings) -> list[dict]:
    """Drive one run; its trace, one dict per control step (time, pose, deviation, steering, the policy's info)."""
    scene, _ = case_scene(run.seed, settings.size)
    centre, _ = ego_lane(scene)
    vehicle, dt = settings.vehicle, 1.0 / settings.control_hz
    state = VehicleState(s=run.start_m, d=centre)
    approach_s = max(run.region[0] - run.start_m, 0.0) / vehicle.speed_mps
    limit_s = 2.0 * approach_s + settings.window_s + settings.after_s + 1.0
    policy.reset()
    trace, entered_at = [], None
    while True:
        image, posed = render_view(run, state, settings.size)
        command, info = policy.act(Observation(image, scene.camera, vehicle.speed_mps, state.t, posed, state.steer))
        deviation = state.d - centre
        trace.append({"t": round(state.t, 6), "s": round(state.s, 6), "d": round(state.d, 6),
                      "deviation": round(deviation, 6), "heading": round(state.heading, 8),
                      "steer_deg": round(math.degrees(state.steer), 5),
                      "command_deg": round(math.degrees(command), 5), **info})
        if entered_at is None and state.s >= run.region[0]:
            entered_at = state.t
        end = entered_at is not None and state.t >= entered_at + settings.window_s + settings.after_s - 1e-9
        off_road = abs(deviation) > OFF_ROAD_M or abs(state.heading) > math.radians(MAX_HEADING_DEG)
        if end or off_road or state.t >= limit_s:
            if off_road:
                trace[-1]["off_road"] = True
            return trace
        state = step(state, command, dt, scene.road, vehicle)
