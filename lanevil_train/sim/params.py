"""SceneParams: every user-settable knob of a rendered scene, validated, and sampled from a seed."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from lanevil_train.rules import check_settings, is_int, number
from lanevil_train.sim.presets import (
    MARKING_STRIPES,
    MARKING_TYPES,
    ROAD_KINDS,
    SCENE_KIND_NAMES,
    SCENE_KINDS,
    WEATHER_NAMES,
)


def _check_range(name: str, value, lo: float, hi: float) -> None:
    check_settings({name: number(lo, hi)}, {name: value}, "SceneParams")


def _check_name(name: str, value, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ValueError(f"SceneParams.{name}: unknown {value!r}, expected one of {list(allowed)}")


@dataclass(frozen=True)
class SceneParams:
    """What a scene looks like; `render_scene(seed, params)` is a pure function of both.

    Geometry: road kind (ROAD_KINDS), curvature magnitude (1/m) for curves, s_curve_flip (m: where
    an S-curve's curvature changes sign), grade magnitude (rise per metre) and slope_start (m) for
    up/downhill. Lanes: num_lanes 2..5, lane_width (m), markings (one name per boundary, left to
    right, num_lanes + 1 of them; None = the scene kind's default layout), ego_lane (0 = leftmost;
    None = middle) and lateral_offset (m, + right) of the camera in it. Look: weather, scene_kind,
    paint_wear 0..1, dash_length / dash_gap (m), travel (m driven; shifts dashes and textures, for
    clips). Camera: camera_height (m), pitch_deg (down +), yaw_deg (right +), hfov_deg.
    """

    road: str = "straight"
    curvature: float = 1.0 / 300.0
    s_curve_flip: float = 45.0
    grade: float = 0.06
    slope_start: float = 20.0
    num_lanes: int = 3
    lane_width: float = 3.5
    markings: tuple[str, ...] | None = None
    ego_lane: int | None = None
    lateral_offset: float = 0.0
    weather: str = "clear_noon"
    scene_kind: str = "urban"
    paint_wear: float = 0.25
    dash_length: float = 3.0
    dash_gap: float = 9.0
    travel: float = 0.0
    camera_height: float = 1.5
    pitch_deg: float = 2.0
    yaw_deg: float = 0.0
    hfov_deg: float = 90.0

    def __post_init__(self) -> None:
        _check_name("road", self.road, ROAD_KINDS)
        _check_name("weather", self.weather, WEATHER_NAMES)
        _check_name("scene_kind", self.scene_kind, SCENE_KIND_NAMES)
        _check_range("curvature", self.curvature, 0.0, 0.02)
        _check_range("s_curve_flip", self.s_curve_flip, 10.0, 500.0)
        _check_range("grade", self.grade, 0.0, 0.15)
        _check_range("slope_start", self.slope_start, 0.0, 200.0)
        if not is_int(self.num_lanes) or not 2 <= self.num_lanes <= 5:
            raise ValueError(f"SceneParams.num_lanes: expected an integer in [2, 5], got {self.num_lanes!r}")
        _check_range("lane_width", self.lane_width, 2.5, 4.5)
        if self.markings is not None:
            if not isinstance(self.markings, tuple) or len(self.markings) != self.num_lanes + 1:
                raise ValueError(
                    f"SceneParams.markings: expected a tuple of num_lanes + 1 = {self.num_lanes + 1} "
                    f"marking names, got {self.markings!r}")
            for i, mk in enumerate(self.markings):
                if mk not in MARKING_STRIPES:
                    raise ValueError(f"SceneParams.markings[{i}]: unknown {mk!r}, expected one of "
                                     f"{list(MARKING_STRIPES)}")
        if self.ego_lane is not None and (not is_int(self.ego_lane) or not 0 <= self.ego_lane < self.num_lanes):
            raise ValueError(f"SceneParams.ego_lane: expected None or an integer in [0, {self.num_lanes - 1}],"
                             f" got {self.ego_lane!r}")
        _check_range("lateral_offset", self.lateral_offset, -1.2, 1.2)
        _check_range("paint_wear", self.paint_wear, 0.0, 1.0)
        _check_range("dash_length", self.dash_length, 0.5, 20.0)
        _check_range("dash_gap", self.dash_gap, 0.5, 40.0)
        _check_range("travel", self.travel, -1e6, 1e6)
        _check_range("camera_height", self.camera_height, 0.5, 5.0)
        _check_range("pitch_deg", self.pitch_deg, -10.0, 15.0)
        _check_range("yaw_deg", self.yaw_deg, -15.0, 15.0)
        _check_range("hfov_deg", self.hfov_deg, 30.0, 130.0)

    @property
    def resolved_markings(self) -> tuple[str, ...]:
        """The marking of each boundary (left to right), defaults filled in from the scene kind."""
        if self.markings is not None:
            return self.markings
        left, inner, right = SCENE_KINDS[self.scene_kind]["markings"]
        return (left,) + (inner,) * (self.num_lanes - 1) + (right,)

    @property
    def resolved_ego_lane(self) -> int:
        """Index of the lane the camera drives in (0 = leftmost)."""
        return self.num_lanes // 2 if self.ego_lane is None else int(self.ego_lane)

    def as_dict(self) -> dict:
        """Plain dict (for metadata / YAML)."""
        out = asdict(self)
        out["markings"] = list(self.resolved_markings)
        return out

    def replace(self, **changes) -> "SceneParams":
        """A copy with some fields changed (validated again)."""
        return replace(self, **changes)


_LEFT_CHOICES = {
    "urban": (("yellow_double_solid", 0.45), ("yellow_solid", 0.2), ("yellow_solid_dashed", 0.15),
              ("white_double_solid", 0.1), ("white_solid", 0.1)),
    "highway": (("yellow_solid", 0.5), ("white_solid", 0.3), ("yellow_double_solid", 0.2)),
    "rural": (("yellow_dashed", 0.35), ("yellow_double_solid", 0.3), ("yellow_solid_dashed", 0.2),
              ("yellow_solid", 0.15)),
}
_INNER_CHOICES = (("white_dashed", 0.75), ("white_solid_dashed", 0.08), ("botts_dots", 0.07),
                  ("white_solid", 0.05), ("white_double_solid", 0.05))
_RIGHT_CHOICES = {
    "urban": (("white_solid", 0.9), ("none", 0.1)),
    "highway": (("white_solid", 0.95), ("white_double_solid", 0.05)),
    "rural": (("white_solid", 0.7), ("none", 0.3)),
}


def _pick(rng: np.random.Generator, choices) -> str:
    names = [c[0] for c in choices]
    p = np.array([c[1] for c in choices], dtype=np.float64)
    return names[int(rng.choice(len(names), p=p / p.sum()))]


def sample_scene_params(seed_or_rng: int | np.random.Generator) -> SceneParams:
    """Random but plausible SceneParams (every road/weather/scene kind/marking type occurs)."""
    rng = seed_or_rng if isinstance(seed_or_rng, np.random.Generator) else np.random.default_rng(
        [int(seed_or_rng), 0x5CE7E])
    kind = SCENE_KIND_NAMES[int(rng.integers(len(SCENE_KIND_NAMES)))]
    road = ROAD_KINDS[int(rng.choice(len(ROAD_KINDS), p=[0.3, 0.15, 0.15, 0.14, 0.13, 0.13]))]
    num_lanes = int(rng.choice([2, 3, 4, 5], p=[0.3, 0.35, 0.25, 0.1]))
    lo, hi = SCENE_KINDS[kind]["lane_width"]
    inner = _pick(rng, _INNER_CHOICES)
    markings = (_pick(rng, _LEFT_CHOICES[kind]),) + (inner,) * (num_lanes - 1) + (
        _pick(rng, _RIGHT_CHOICES[kind]),)
    return SceneParams(
        road=road,
        curvature=float(1.0 / np.exp(rng.uniform(np.log(180.0), np.log(900.0)))),
        s_curve_flip=float(rng.uniform(30.0, 70.0)),
        grade=float(rng.uniform(0.03, 0.09)),
        slope_start=float(rng.uniform(10.0, 40.0)),
        num_lanes=num_lanes,
        lane_width=float(rng.uniform(lo, hi)),
        markings=markings,
        ego_lane=int(rng.integers(num_lanes)),
        lateral_offset=float(np.clip(rng.normal(0.0, 0.25), -0.6, 0.6)),
        weather=WEATHER_NAMES[int(rng.integers(len(WEATHER_NAMES)))],
        scene_kind=kind,
        paint_wear=float(rng.uniform(0.0, 0.6)),
        dash_length=float(rng.choice([3.0, 3.0, 4.0, 6.0])),
        dash_gap=float(rng.choice([9.0, 9.0, 6.0, 12.0])),
        travel=float(rng.uniform(0.0, 1000.0)),
        camera_height=float(rng.uniform(1.3, 1.7)),
        pitch_deg=float(rng.uniform(0.5, 3.5)),
        yaw_deg=float(rng.uniform(-1.5, 1.5)),
        hfov_deg=90.0,
    )


__all__ = ["SceneParams", "sample_scene_params", "MARKING_TYPES"]
