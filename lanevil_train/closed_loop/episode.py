"""One closed-loop run: the car starts before an illusion, a policy steers it from its camera, the trace is kept.

Each control step renders the camera view from the car's true pose (arc length s, lateral offset d, heading:
sim.scene_at), draws the run's illusion into it from that pose (laid out once in the case's reference view, so it
stays where it is on the road: illusions.context_for_frame), asks the policy for a steering angle, with
longitudinal control (`longitudinal=acc`, closed_loop/longitudinal.py) asks the ACC and emergency brake for an
acceleration from the radar's range to the nearest object in the policy's corridor, and moves the car by the
bicycle model (sim.vehicle) for one control period. A run ends `window_s + after_s` after the car entered the
illusion region, when it has left the road (|deviation| > OFF_ROAD_M, or a heading of MAX_HEADING_DEG to the
road), when it has stood still for STOPPED_END_S (braked to a stop before an object), or at its time limit (twice
the approach at the set speed, the windows and 1 s). A clean twin drives the same start with no illusion.

With `longitudinal=none` the car keeps its set speed and the trace is as it always was; with `acc` each step also
keeps speed_mps (m/s, at the step), accel_mps2 (the command over the next period), radar_m (m from the front
bumper to the nearest object in the corridor; None: none there) and aeb (the emergency brake is on).

The illusion region of a case and illusion is its footprint on the road at REGION_SEVERITY in the reference view
(illusions.footprint): every severity and the clean twin share it, their start and their attack window.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from lanevil_train.closed_loop.collisions import Obstacle, obstacles
from lanevil_train.closed_loop.longitudinal import MODES, AccSettings, Longitudinal, radar_range, straight_corridor
from lanevil_train.closed_loop.policies import Observation, Policy
from lanevil_train.illusions.context import context_for_frame, context_from_scene
from lanevil_train.illusions.footprint import STANDING, footprint
from lanevil_train.illusions.registry import get_illusion
from lanevil_train.rules import check_settings, int_pair, number, one_of
from lanevil_train.sim import Scene, build_scene, sample_scene_params, shade_scene
from lanevil_train.sim.sequence import MAX_VIEW_HEADING_DEG, scene_at
from lanevil_train.sim.vehicle import VehicleParams, VehicleState, step
from lanevil_train.taxonomy import ILLUSION_CATEGORY

REGION_SEVERITY = 3
OFF_ROAD_M = 3.0
MAX_HEADING_DEG = 35.0
STOPPED_END_S = 1.0  # a car that has stood still this long ends its run (it waits behind a standing object)


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
    point: tuple[tuple[str, float], ...] | None = None  # a point of the illusion's parameters, (name, value) pairs,
    # drawn instead of the severity (task=search; Illusion.render_point)

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
    """Image size (H, W), control rate (Hz), attack window and what is driven after it (s), the vehicle, the
    longitudinal control (acc: ACC and emergency brake with `acc`'s settings; none: the set speed throughout)."""

    SETTINGS = {"size": int_pair(32), "control_hz": number(0, 100, low_open=True),
                "window_s": number(0, low_open=True), "after_s": number(0),
                "longitudinal": one_of(*MODES)}  # task.<name> of task=closed_loop

    size: tuple[int, int] = (360, 640)
    control_hz: float = 10.0
    window_s: float = 2.5
    after_s: float = 0.5
    vehicle: VehicleParams = field(default_factory=VehicleParams)
    longitudinal: str = "acc"
    acc: AccSettings = field(default_factory=AccSettings)

    def __post_init__(self) -> None:
        check_settings(self.SETTINGS, {name: getattr(self, name) for name in self.SETTINGS}, "task")
        if self.acc.decel_mps2 > self.vehicle.max_decel_mps2:
            raise ValueError(f"task.acc.decel_mps2: expected at most task.vehicle.max_decel_mps2 "
                             f"({self.vehicle.max_decel_mps2:g}, the brakes' limit), got {self.acc.decel_mps2:g}")

    def longitudinal_control(self) -> Longitudinal | None:
        """A new run's ACC and emergency brake, or None without longitudinal control."""
        return Longitudinal(self.acc, self.vehicle, 1.0 / self.control_hz) if self.longitudinal == "acc" else None

    def run_up_m(self) -> float:
        """How much earlier a run with objects on the road starts (m; 0 without longitudinal control)."""
        return self.acc.run_up_m(self.vehicle, 1.0 / self.control_hz) if self.longitudinal == "acc" else 0.0


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


@lru_cache(maxsize=8)
def region_render(seed: int, illusion: str, size: tuple[int, int]) -> tuple[Scene, np.ndarray, np.ndarray]:
    """The case's scene, its clean reference image and that image with the illusion at REGION_SEVERITY: where the
    illusion region (illusion_region) and its footprint edges (time_scores.illusion_edges) are read."""
    scene, clean = case_scene(seed, size)
    return scene, clean, get_illusion(illusion)(clean, context_from_scene(scene), REGION_SEVERITY, seed)


def illusion_region(seed: int, illusion: str, size: tuple[int, int]) -> tuple[float, float]:
    """(near, far) arc lengths (m) of the illusion's footprint on the road of the case's reference view."""
    area = footprint(*region_render(seed, illusion, size), standing=illusion in STANDING)
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
    if run.severity or run.point is not None:
        context = context_for_frame(scene, state.s, reference, state.d, state.heading)
        illusion = get_illusion(run.illusion)
        image = (illusion.render_point(image, context, dict(run.point), run.seed) if run.point is not None
                 else illusion(image, context, run.severity, run.seed))
    return image, posed


def drive(run: Run, policy: Policy, settings: LoopSettings, objects: Sequence[Obstacle] | None = None) -> list[dict]:
    """Drive one run; its trace, one dict per control step (time, pose, deviation, steering, the policy's info).
    `objects`: what the radar sees (default: the run's obstacles, run_obstacles; they are not drawn)."""
    scene, _ = case_scene(run.seed, settings.size)
    centre, _ = ego_lane(scene)
    vehicle, dt = settings.vehicle, 1.0 / settings.control_hz
    state = VehicleState(s=run.start_m, d=centre, speed=vehicle.speed_mps)
    approach_s = max(run.region[0] - run.start_m, 0.0) / vehicle.speed_mps
    limit_s = 2.0 * approach_s + settings.window_s + settings.after_s + 1.0
    longitudinal = settings.longitudinal_control()
    if objects is None:
        objects = run_obstacles(run.seed, run.illusion, run.severity, settings.size) if longitudinal else ()
    policy.reset()
    trace, entered_at, stopped_at = [], None, None
    while True:
        if abs(state.heading) >= math.radians(MAX_VIEW_HEADING_DEG):
            # one period turned the car past what a view can show (from under MAX_HEADING_DEG): it has left the
            # road's direction; the pose ends the trace, with no image, no policy and the last steering held
            trace.append({**_pose(state, centre), "command_deg": trace[-1]["command_deg"], "off_road": True})
            return trace
        image, posed = render_view(run, state, settings.size)
        speed = state.speed_mps(vehicle)
        command, info = policy.act(Observation(image, scene.camera, speed, state.t, posed, state.steer))
        accel, motion = 0.0, {}
        if longitudinal is not None:
            accel, radar = longitudinal.command(speed, _radar(state, posed, objects, policy, settings))
            motion = {"speed_mps": round(speed, 6), **radar}
        deviation = state.d - centre
        trace.append({**_pose(state, centre), "command_deg": round(math.degrees(command), 5), **motion, **info})
        if entered_at is None and state.s >= run.region[0]:
            entered_at = state.t
        if speed > 0.0:
            stopped_at = None
        elif stopped_at is None:
            stopped_at = state.t  # it has stood still since
        end = entered_at is not None and state.t >= entered_at + settings.window_s + settings.after_s - 1e-9
        off_road = abs(deviation) > OFF_ROAD_M or abs(state.heading) > math.radians(MAX_HEADING_DEG)
        stopped = stopped_at is not None and state.t >= stopped_at + STOPPED_END_S - 1e-9
        if end or off_road or stopped or state.t >= limit_s:
            if off_road:
                trace[-1]["off_road"] = True
            if stopped:
                trace[-1]["stopped"] = True
            return trace
        state = step(state, command, dt, scene.road, vehicle, accel)


def _pose(state: VehicleState, centre: float) -> dict:
    """A trace step's pose: time, arc length, offset, deviation from the lane centre, heading, wheel angle."""
    return {"t": round(state.t, 6), "s": round(state.s, 6), "d": round(state.d, 6),
            "deviation": round(state.d - centre, 6), "heading": round(state.heading, 8),
            "steer_deg": round(math.degrees(state.steer), 5)}


def _radar(state: VehicleState, posed: Scene, objects: Sequence[Obstacle], policy: Policy,
           settings: LoopSettings) -> float | None:
    """The radar's range (m) to the nearest object in the policy's corridor (its tracked lane, else straight
    ahead of the default lane width), None when none is there."""
    if not objects:
        return None
    corridor = getattr(policy, "corridor", lambda: None)() or straight_corridor(settings.acc.lane_width_m)
    return radar_range(state, posed, objects, corridor, settings.acc.corridor_margin_m, settings.vehicle.wheelbase_m)
