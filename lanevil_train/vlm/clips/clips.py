"""Scene videos for the VLM benchmark: a camera driving through an illusion, cut into 3 clips of 6 frames.

A case (`ClipCase`) is a scene seed and the one illusion type its video is built around. The scene
is `sample_scene_params(seed)`; its single-image view is the *reference view*: the illusion is laid
out there exactly as in the image benchmark (same seed, same placement rules), once, in road
coordinates. A frame is the scene seen from a camera pose s metres further along the centre line
(`sim.sequence`: curves and slopes are followed, dashes and textures move past), and the illusion is
drawn into it from that pose (`illusions.context_for_frame`), so it stays put on the road.

Where the illusion lies is read from the renderer itself: the pixels where the reference view with
the illusion at severity TRUTH_SEVERITY (the items every severity shares) differs from the clean one,
inverse-projected onto the road (for standing objects, traffic and guard rails, the lowest changed
pixel of each column, where they meet the ground). That gives its near end and far end (arc length
from the reference camera) and the lane it lies in.

Camera positions. The car drives at SPEED_MPS of the scene kind (urban 10 m/s, rural 12.5, highway
15), frames FRAME_INTERVAL_S = 0.4 s apart (4-6 m), so a clip covers 2 s of driving. With `near` and
`far` the illusion's ends and `step` the frame spacing, the clips start at:
  * before: the last frame still BEFORE_GAP_M (10 m) short of the near end (25 m for traffic), the
    illusion ahead in every frame;
  * over: surface illusions (damage, shadows, reflections, guard rails): the camera reaches the near
    end between frames 2 and 3 and drives onto it; traffic, which stands on the lane lines: the
    last frame 8 m short of it (closing in);
  * alongside: surface illusions: the stretch up to the far end (the last frame at `far`, but
    starting 1 to 5 steps after `over` starts); traffic: the last frame 0.5 m short of it, passing it
    (4 m short when it stands in the ego lane or across lanes: the car stops behind it).
Each clean frame is rendered once and the illusion drawn into it at every requested severity with
the case seed, so a clean/perturbed pair differs only where the illusion acts.

Suite kinds (perturbations.SUITE_KINDS; `suite_cases` gives a kind's case list, `render_variants` its frames):
  * illusions: each case's own illusion (`render_clip`);
  * corruptions: the case still places the camera, but its illusion is not drawn: the clean frames get each
    non-illusion corruption instead, frame k with `frame_seed` (rain and noise change from frame to frame);
  * combined (paper §5.6): a case also names a `second` illusion of another category, drawn into the same frames
    from the same frame context after the first (`combined_clip_cases`: case i takes the i-th category pair).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from itertools import combinations

import numpy as np

from lanevil_train.illusions.context import context_for_frame, context_from_scene
from lanevil_train.illusions.footprint import STANDING, Footprint, changed_road_points, footprint, lane_of  # noqa: F401  (changed_road_points, lane_of: part of this API)
from lanevil_train.illusions.registry import check_seed, get_illusion
from lanevil_train.perturbations import (
    Combined,
    check_kind,
    combined_choice,
    get_perturbation,
    suite_names,
)
from lanevil_train.sim import Scene, build_scene, sample_scene_params, shade_scene
from lanevil_train.sim.presets import WEATHERS, marking_color
from lanevil_train.sim.sequence import scene_at
from lanevil_train.taxonomy import CATEGORIES, ILLUSION_CATEGORY, ILLUSION_NAMES

SEGMENTS = ("before", "over", "alongside")
FRAMES_PER_CLIP = 6
FRAME_INTERVAL_S = 0.4
SPEED_MPS = {"urban": 10.0, "rural": 12.5, "highway": 15.0}
TRUTH_SEVERITY = 1
BEFORE_GAP_M = 10.0
OBSTACLE_GAPS_M = {"before": 25.0, "over": 8.0, "alongside": 0.5}  # last frame this far short of traffic
BLOCKED_GAP_M = 4.0  # ... or this far when it stands in the ego lane
OBSTACLES = frozenset(("pedestrian", "vehicle", "bicycle"))  # the car passes them, never drives over them
DEFAULT_SIZE = (360, 640)


@dataclass(frozen=True)
class ClipCase:
    """One scene video: a scene seed and the one illusion type it is built around (it places the camera and
    drives the QA); a combined-suite case also names the `second` illusion, of another category, drawn over it."""

    case_id: str
    seed: int
    illusion: str
    second: str | None = None

    def __post_init__(self) -> None:
        check_seed(self.seed)
        get_illusion(self.illusion)
        if self.second is not None:
            get_illusion(self.second)
            if ILLUSION_CATEGORY[self.second] == ILLUSION_CATEGORY[self.illusion]:
                raise ValueError(f"second: expected an illusion of another category than {self.illusion!r} "
                                 f"({ILLUSION_CATEGORY[self.illusion]}), got {self.second!r}")


def clip_cases(num_cases: int, first_seed: int, illusions: Sequence[str]) -> list[ClipCase]:
    """Case i: seed first_seed + i, illusion illusions[i % len(illusions)] (a suite covers every type)."""
    if isinstance(num_cases, bool) or not isinstance(num_cases, (int, np.integer)) or num_cases < 0:
        raise ValueError(f"num_cases: expected an integer >= 0, got {num_cases!r}")
    check_seed(first_seed)
    names = [illusions] if isinstance(illusions, str) else list(illusions)
    if not names:
        raise ValueError(f"illusions: expected at least one name of {list(ILLUSION_NAMES)}, got none")
    for i, name in enumerate(names):
        if name not in ILLUSION_NAMES:
            raise ValueError(f"illusions[{i}]: unknown {name!r}, expected one of {list(ILLUSION_NAMES)}")
    return [ClipCase(f"clip-{first_seed + i}", int(first_seed + i), names[i % len(names)])
            for i in range(int(num_cases))]


def category_pairs(illusions: Sequence[str]) -> list[tuple[str, str]]:
    """The category pairs the illusions span, in the paper's order (RD+TO, RD+SH, RD+RF, TO+SH, TO+RF, SH+RF)."""
    present = [c for c, members in CATEGORIES.items() if any(n in illusions for n in members)]
    return list(combinations(present, 2))


def combined_clip_cases(num_cases: int, first_seed: int, illusions: str | Sequence[str] = "all") -> list[ClipCase]:
    """Combined-suite cases: case i has seed first_seed + i and the (i mod P)-th of the P category pairs its
    illusions span, so consecutive cases cover the pairs evenly; its own illusion is of the pair's first category,
    its second of the other, each the one perturbations.combined_choice draws from the seed for that category."""
    if isinstance(num_cases, bool) or not isinstance(num_cases, (int, np.integer)) or num_cases < 0:
        raise ValueError(f"num_cases: expected an integer >= 0, got {num_cases!r}")
    check_seed(first_seed)
    names = suite_names("combined", illusions)
    pairs = category_pairs(names)
    out = []
    for i in range(int(num_cases)):
        seed = int(first_seed + i)
        drawn = {ILLUSION_CATEGORY[n]: n for n in combined_choice(seed, names)[0]}
        first, second = pairs[i % len(pairs)]
        out.append(ClipCase(f"clip-{seed}", seed, drawn[first], drawn[second]))
    return out


def suite_cases(kind: str, num_cases: int, first_seed: int, names: str | Sequence[str] = "all") -> list[ClipCase]:
    """The cases of a `kind` suite: clip_cases over `names` (illusions), over every illusion, which then only
    places the camera (corruptions: `names` are corruptions), or combined_clip_cases (combined)."""
    if check_kind(kind) == "combined":
        return combined_clip_cases(num_cases, first_seed, names)
    names = suite_names(kind, names)
    return clip_cases(num_cases, first_seed, names if kind == "illusions" else ILLUSION_NAMES)


def _check_size(size) -> tuple[int, int]:
    """(H, W) of positive integers, or a ValueError naming `size`."""
    ok = isinstance(size, (tuple, list)) and len(size) == 2 and all(
        isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 16 for v in size)
    if not ok:
        raise ValueError(f"size: expected (height, width) in pixels, each >= 16, got {size!r}")
    return int(size[0]), int(size[1])


def _check_segment(segment: str) -> str:
    if segment not in SEGMENTS:
        raise ValueError(f"segment: expected one of {list(SEGMENTS)}, got {segment!r}")
    return segment


def _check_case(case) -> ClipCase:
    if not isinstance(case, ClipCase):
        raise ValueError(f"case: expected a ClipCase, got {type(case).__name__}")
    return case


def reference_scene(case: ClipCase, size=DEFAULT_SIZE) -> Scene:
    """The case's scene seen from the reference pose (where its illusion is laid out)."""
    h, w = _check_size(size)
    return build_scene(case.seed, sample_scene_params(case.seed), w, h)


@lru_cache(maxsize=16)
def _reference(seed: int, illusion: str, size: tuple[int, int]) -> tuple[np.ndarray, Footprint]:
    """The clean reference image and the illusion's footprint (cached: every segment needs them)."""
    scene = reference_scene(ClipCase(f"clip-{seed}", seed, illusion), size)
    clean = shade_scene(scene)
    perturbed = get_illusion(illusion)(clean, context_from_scene(scene), TRUTH_SEVERITY, seed)
    return clean, footprint(scene, clean, perturbed, standing=illusion in STANDING)


def frame_step_m(scene: Scene) -> float:
    """Metres driven between frames (the scene kind's speed times FRAME_INTERVAL_S)."""
    return SPEED_MPS[scene.params.scene_kind] * FRAME_INTERVAL_S


def segment_positions(case: ClipCase, segment: str, size=DEFAULT_SIZE) -> np.ndarray:
    """Camera arc lengths (m from the reference pose) of the clip's FRAMES_PER_CLIP frames."""
    _check_segment(segment)
    scene = reference_scene(_check_case(case), size)
    step = frame_step_m(scene)
    fp = _reference(case.seed, case.illusion, _check_size(size))[1]
    span = (FRAMES_PER_CLIP - 1) * step
    if case.illusion in OBSTACLES:
        gap = OBSTACLE_GAPS_M[segment]
        if segment == "alongside" and fp.lane in ("ego", "across"):
            gap = BLOCKED_GAP_M  # it blocks the ego lane: the car closes in and stops short of it
        start = fp.near_m - gap - span
    elif segment == "before":
        start = fp.near_m - BEFORE_GAP_M - span
    elif segment == "over":
        start = fp.near_m - 0.5 * span
    else:
        over = fp.near_m - 0.5 * span
        start = float(np.clip(fp.far_m - span, over + step, over + span))
    return start + step * np.arange(FRAMES_PER_CLIP)


def _check_severities(severities) -> list[int]:
    if isinstance(severities, (str, bytes)) or not isinstance(severities, Sequence) or not severities:
        raise ValueError(f"severities: expected a non-empty list of integers 0 (clean) .. 5, got {severities!r}")
    for i, sev in enumerate(severities):
        if isinstance(sev, bool) or not isinstance(sev, (int, np.integer)) or not 0 <= sev <= 5:
            raise ValueError(f"severities[{i}]: expected an integer 0 (clean) .. 5, got {sev!r}")
    return [int(v) for v in severities]


def render_clip(case: ClipCase, segment: str, severities: Sequence[int],
                size=DEFAULT_SIZE) -> dict[int, list[np.ndarray]]:
    """{severity: 6 uint8 HxWx3 RGB frames}; severity 0 is the clean clip. Each clean frame is rendered
    once and the illusion drawn into it at every requested severity with the case seed."""
    sevs = _check_severities(severities)
    variants = render_variants(case, segment, [_check_case(case).illusion], sevs, size)
    return {sev: variants[(case.illusion if sev else None, sev)] for sev in sevs}


def frame_seed(seed: int, segment: str, k: int) -> int:
    """The seed of frame k of a case's `segment` clip for image-space corruptions: fixed by the case seed, different
    for every frame and segment (rain streaks and sensor noise do not stand still)."""
    state = np.random.SeedSequence([check_seed(seed), SEGMENTS.index(_check_segment(segment)), int(k)])
    return int(state.generate_state(1)[0] >> 1)


def render_variants(case: ClipCase, segment: str, names: Sequence[str], severities: Sequence[int],
                    size=DEFAULT_SIZE) -> dict[tuple[str | None, int], list[np.ndarray]]:
    """{(None, 0): the 6 clean frames, (name, severity): those frames with perturbation `name` (an illusion, a
    corruption or a pair "a+b": perturbations.get_perturbation)} for every name and non-zero severity. Each clean
    frame is rendered once; illusions and pairs are drawn from the frame's pose with the case seed (they stay put on
    the road), corruptions with frame_seed; a pair reuses its first illusion's frames when those are asked for too."""
    sevs = [s for s in dict.fromkeys(_check_severities(severities)) if s]
    if isinstance(names, str) or not isinstance(names, Sequence):
        raise ValueError(f"names: expected a list of perturbation names, got {names!r}")
    perturbations = []
    for i, name in enumerate(names):
        try:
            perturbations.append(get_perturbation(name))
        except ValueError as error:
            raise ValueError(f"names[{i}]: {error}") from error
    size = _check_size(size)
    scene = reference_scene(_check_case(case), size)
    ref_clean = _reference(case.seed, case.illusion, size)[0]
    out: dict[tuple[str | None, int], list[np.ndarray]] = {(None, 0): []}
    out.update({(p.name, sev): [] for p in perturbations for sev in sevs})
    for k, s0 in enumerate(segment_positions(case, segment, size)):
        clean = shade_scene(scene_at(scene, float(s0)))
        ctx = context_for_frame(scene, float(s0), ref_clean)
        out[(None, 0)].append(clean)
        for p in perturbations:
            in_world = isinstance(p, Combined) or p.name in ILLUSION_CATEGORY
            seed = case.seed if in_world else frame_seed(case.seed, segment, k)
            for sev in sevs:
                first = out.get((p.first.name, sev), []) if isinstance(p, Combined) else []
                frame = p.second(first[k], ctx, sev, seed) if len(first) > k else p(clean, ctx, sev, seed)
                out[(p.name, sev)].append(frame)
    return out


def _curvature_sign(scene: Scene, positions: np.ndarray) -> int:
    """Sign of the mean curvature of the road over the clip and 30 m ahead of it (0: nearly straight)."""
    s = np.linspace(positions[0], positions[-1] + 30.0, 64)
    k = float(np.mean(scene.road.k + scene.road.j * s))
    return 0 if abs(k) < 1.0 / 2000.0 else (1 if k > 0 else -1)


def _slope(scene: Scene, positions: np.ndarray) -> str:
    """'uphill' / 'downhill' when the clip's stretch (and 40 m ahead) reaches the slope, else 'flat'."""
    road = scene.road
    if road.grade == 0.0 or positions[-1] + 40.0 < road.slope_start:
        return "flat"
    return "uphill" if road.grade > 0 else "downhill"


def _polylines(scene: Scene) -> list[list[list[float]]]:
    """GT lane polylines of a frame as plain lists, 0.1 px precision."""
    return [np.round(line, 1).tolist() for line in scene.lanes()[0]]


def clip_truth(case: ClipCase, segment: str, size=DEFAULT_SIZE) -> dict:
    """The scene's ground truth over one clip, plain JSON values (for QA templates); see the module doc."""
    size = _check_size(size)
    scene = reference_scene(_check_case(case), size)
    positions = segment_positions(case, segment, size)
    fp = _reference(case.seed, case.illusion, size)[1]
    params, weather = scene.params, WEATHERS[scene.params.weather]
    frames = [scene_at(scene, float(s0)) for s0 in positions]
    lanes_px = [_polylines(f) for f in frames]
    markings = list(params.resolved_markings)
    return {
        "case_id": case.case_id, "seed": case.seed, "segment": segment,
        "road": params.road, "curvature_sign": _curvature_sign(scene, positions), "slope": _slope(scene, positions),
        "num_lanes": int(params.num_lanes), "lane_width_m": float(params.lane_width),
        "ego_lane": int(params.resolved_ego_lane), "markings": markings,
        "marking_colors": [marking_color(m) for m in markings],
        "num_lane_lines": [len(lines) for lines in lanes_px],
        "weather": params.weather, "night": bool(weather["night"]), "wet": float(weather["wet"]),
        "scene_kind": params.scene_kind,
        "illusion": case.illusion, "category": ILLUSION_CATEGORY[case.illusion],
        "illusion_lane": fp.lane, "illusion_found": fp.found,
        "illusion_distance_m": [round(fp.near_m - float(s0), 2) for s0 in positions],
        "illusion_extent_m": round(fp.far_m - fp.near_m, 2),
        "ego_speed_mps": SPEED_MPS[params.scene_kind], "frame_step_m": frame_step_m(scene),
        "frame_s_m": [round(float(s0), 2) for s0 in positions],
        "lanes_px": lanes_px,
    }
