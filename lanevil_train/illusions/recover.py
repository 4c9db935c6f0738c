"""Recover an IllusionContext from a real photo's annotated lanes (TuSimple / CULane).

Model: a flat, straight road and a pinhole camera with its principal point at the image centre and
a known horizontal FOV (as `lanevil_train.sim.Camera`). The near, straight part of each lane is fitted
with a line; the lines meet at the vanishing point (VP) of the road direction, which fixes the
camera pitch (VP row) and yaw (VP column). Back-projecting the lanes onto the ground with a trial
camera height gives their lateral offsets up to one common scale.

Scale rule: on a flat road the lane width and the camera height only fix each other's ratio, so one
of them must be assumed. `lane_width` wins: the median spacing of adjacent lanes is set to it and
the camera height follows. Pass `lane_width=None` to take `camera_height` as given instead (the lane
offsets then follow from it).

When the lanes cannot give a ground plane (fewer than two usable lanes, parallel lines, a VP below
the lanes, an implausible pitch) a GroundPlaneError says why; `fallback_context` then builds an
explicit default camera and road instead.
"""

from __future__ import annotations

import math

import numpy as np

from lanevil_train.illusions.context import IllusionContext

# re-exported: the margins, documented in lanevil_train.lanes (illusions/api.py refers to them here)
from lanevil_train.lanes import INVALID_X, LANE_X_MARGIN_FRAC, LANE_Y_MARGIN_FRAC, lane_extent_problem  # noqa: F401
from lanevil_train.sim import Camera, RoadGeometry
from lanevil_train.sim.presets import MARKING_STRIPES
from lanevil_train.sim.road import Boundary

# Default sun: the simulator's "clear_noon" sun (elevation 60 deg, azimuth 25 deg to the right of
# the road direction); at night a sun 30 deg below the horizon, as in the simulator's "night".
DAY_SUN_ELEV_AZIM_DEG = (60.0, 25.0)
NIGHT_SUN_ELEV_AZIM_DEG = (-30.0, 0.0)

MIN_LANE_POINTS = 5            # a lane needs at least this many points to be fitted
MIN_LANE_SPAN_FRAC = 0.04      # ... and to span at least this fraction of the image height
NEAR_FRAC = 0.2                # near band: rows below 20 % of the way from the VP row to the bottom
MIN_ANGLE_DEG = 1.0            # lines closer in image direction than this count as parallel
MAX_PITCH_DEG = 30.0           # |pitch| beyond this is implausible for a road camera
MAX_YAW_DEG = 45.0             # |yaw| beyond this too (and outside Camera's valid range)
SHOULDER_M = 1.0               # asphalt beyond the outermost recovered lane
# LANE_X_MARGIN_FRAC / LANE_Y_MARGIN_FRAC (imported above): how far lane points may lie outside the image;
# lanevil_train.lanes.lane_extent_problem is the check, shared with the datasets.
_TRIAL_HEIGHT = 1.0            # camera height used for back-projection before scaling
_MARKING = "white_solid"       # the marking assumed for every recovered lane (type is unknown)


class GroundPlaneError(ValueError):
    """The annotated lanes do not determine a ground plane (use `fallback_context` instead)."""


def _sun(sun_direction: np.ndarray | None, night: bool) -> np.ndarray:
    """A unit sun vector: the given one normalised, or the documented day / night default."""
    if sun_direction is None:
        el, az = (math.radians(v) for v in (NIGHT_SUN_ELEV_AZIM_DEG if night else DAY_SUN_ELEV_AZIM_DEG))
        return np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    vec = np.asarray(sun_direction, dtype=np.float64).reshape(-1)
    norm = float(np.linalg.norm(vec)) if vec.shape == (3,) else 0.0
    if vec.shape != (3,) or not np.all(np.isfinite(vec)) or norm < 1e-9:
        raise ValueError(f"sun_direction: expected a finite non-zero 3-vector, got {sun_direction!r}")
    return vec / norm


def _check_size(image_size) -> tuple[int, int]:
    """Validate image_size = (height, width) in pixels."""
    try:
        h, w = (int(v) for v in image_size)
        ok = all(float(v) == int(v) for v in image_size) and h > 0 and w > 0
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"image_size: expected (height, width) positive integers, got {image_size!r}")
    return h, w


def _check_wet(wet: float) -> float:
    if not isinstance(wet, (int, float, np.integer, np.floating)) or not 0.0 <= float(wet) <= 1.0:
        raise ValueError(f"wet: expected a number in [0, 1], got {wet!r}")
    return float(wet)


def _road(center_x: float, offsets: np.ndarray, shoulder: float = SHOULDER_M) -> RoadGeometry:
    """A straight flat road along world z, centre line at x = center_x, one boundary per offset.

    When the camera (x = 0) drives outside the annotated lanes (its lane's outer line is not
    annotated, e.g. an unmarked road edge), an unmarked boundary one lane further out keeps the
    camera's own lane on the asphalt."""
    stripes = MARKING_STRIPES[_MARKING]
    boundaries = [Boundary(d=float(d), marking=_MARKING, stripes=stripes, color="white") for d in offsets]
    d_cam = -float(center_x)
    spacing = float(np.median(np.diff(offsets))) if len(offsets) >= 2 else 3.6
    if d_cam > offsets[-1]:
        boundaries.append(Boundary(d=max(float(offsets[-1]) + spacing, d_cam + spacing / 2), marking="none",
                                   stripes=(), color="none"))
    if d_cam < offsets[0]:
        boundaries.insert(0, Boundary(d=min(float(offsets[0]) - spacing, d_cam - spacing / 2), marking="none",
                                      stripes=(), color="none"))
    return RoadGeometry(x0=float(center_x), boundaries=tuple(boundaries), shoulder=shoulder)


# ----------------------------------------------------------------------------- lane fitting
def _check_in_image(i: int, pts: np.ndarray, h: int, w: int) -> None:
    """Raise GroundPlaneError unless lane i's points (N, 2) lie in the h x w image (within the margins)."""
    problem = lane_extent_problem(pts, h, w)
    if problem is not None:
        raise GroundPlaneError(f"lanes[{i}]: {problem}")


def _usable_lanes(lanes: list[np.ndarray], h: int, w: int) -> list[np.ndarray]:
    """Points of each lane, y descending; lanes too short to fit are dropped. Raises on a lane with
    non-finite coordinates or outside the image (see LANE_X_MARGIN_FRAC)."""
    out = []
    for i, lane in enumerate(lanes):
        arr = np.asarray(lane, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 2:
            raise ValueError(f"lanes[{i}]: expected an (N, 2) array of (x, y) points, got shape {arr.shape}")
        finite = np.isfinite(arr)
        if not finite.all():
            k = int(np.argmin(finite.all(axis=1)))
            raise ValueError(f"lanes[{i}]: point {k} is ({arr[k, 0]}, {arr[k, 1]}); expected finite (x, y) pixel "
                             f"coordinates (leave a row without a point out, or give x = {INVALID_X:g} as TuSimple "
                             f"does)")
        arr = arr[arr[:, 0] != INVALID_X]  # drops TuSimple's x = -2 ("no point on this row")
        _check_in_image(i, arr, h, w)
        arr = arr[np.argsort(-arr[:, 1], kind="stable")]
        if len(arr) >= MIN_LANE_POINTS and arr[0, 1] - arr[-1, 1] >= MIN_LANE_SPAN_FRAC * h:
            out.append(arr)
    return out


def _fit(pts: np.ndarray) -> np.ndarray:
    """Least-squares [a, b] of the line x = a*y + b through points (N, 2)."""
    design = np.stack([pts[:, 1], np.ones(len(pts))], axis=1)
    sol, *_ = np.linalg.lstsq(design, pts[:, 0], rcond=None)
    return sol


def _fit_lines(lanes: list[np.ndarray], vp_row: float | None = None) -> tuple[np.ndarray, list[np.ndarray]]:
    """Lines x = a*y + b over each lane's near part; (K, 2) [a, b] and the points used.

    Without vp_row the near part is below the lanes' common far limit (the lowest of the lanes'
    top ends), so every lane is fitted over the same image band. With an estimated vanishing row
    it is the band below NEAR_FRAC of the way from that row to the lowest lane point (the first
    ~10-15 m on a flat road), where curves and hills have not yet bent the lanes. A lane with too
    few points there keeps its lowest MIN_LANE_POINTS points.
    """
    if vp_row is None:
        limit = max(float(lane[:, 1].min()) for lane in lanes)
    else:
        bottom = max(float(lane[:, 1].max()) for lane in lanes)
        limit = vp_row + NEAR_FRAC * (bottom - vp_row)
    coefs, used = [], []
    for lane in lanes:
        pts = lane[lane[:, 1] >= limit]
        if len(pts) < MIN_LANE_POINTS:
            pts = lane[:MIN_LANE_POINTS]
        coefs.append(_fit(pts))
        used.append(pts)
    return np.asarray(coefs), used


def _intersect(coefs: np.ndarray) -> np.ndarray:
    """Least-squares intersection (u, v) of the lines x = a*y + b (perpendicular distances)."""
    a, b = coefs[:, 0], coefs[:, 1]
    norm = np.sqrt(1.0 + a * a)  # line i: n_i . (u, v) = b_i / |(1, -a_i)|, n_i = (1, -a_i) / |.|
    normals = np.stack([1.0 / norm, -a / norm], axis=1)
    vp, *_ = np.linalg.lstsq(normals, b / norm, rcond=None)
    return vp


def _check_vp(coefs: np.ndarray, vp: np.ndarray, used: list[np.ndarray], strict: bool = True) -> None:
    """Raise GroundPlaneError for parallel lines or lines that do not meet above the lanes (strict:
    above every point used; else above the lanes' lowest points, as a hill may lift their far ends)."""
    angles = np.degrees(np.arctan(coefs[:, 0]))
    if float(angles.max() - angles.min()) < MIN_ANGLE_DEG:
        raise GroundPlaneError(
            f"lanes: the fitted lane lines are (nearly) parallel in the image (directions span "
            f"{angles.max() - angles.min():.2f} deg < {MIN_ANGLE_DEG} deg), so there is no finite vanishing "
            f"point; use fallback_context(image_size, ...) for an explicit default camera")
    top = min(float(p[:, 1].min() if strict else p[:, 1].max()) for p in used)
    if not np.all(np.isfinite(vp)) or vp[1] >= top:
        raise GroundPlaneError(
            f"lanes: the lane lines meet at image row {vp[1]:.1f}, not above the lanes (their top is row "
            f"{top:.1f}), so they do not recede into a ground plane; use fallback_context(image_size, ...)")


def _vanishing_point(lanes: list[np.ndarray]) -> tuple[np.ndarray, list[np.ndarray]]:
    """Vanishing point (u, v) of the lanes' near parts (two passes: whole band, then near band)."""
    coefs, used = _fit_lines(lanes)
    vp = _intersect(coefs)
    _check_vp(coefs, vp, used, strict=False)
    coefs, used = _fit_lines(lanes, vp_row=float(vp[1]))
    vp = _intersect(coefs)
    _check_vp(coefs, vp, used)
    return vp, used


# ----------------------------------------------------------------------------- public API
def context_from_lanes(lanes: list[np.ndarray], image_size: tuple[int, int], lane_width: float | None = 3.6,
                       camera_height: float = 1.5, hfov_deg: float = 90.0,
                       sun_direction: np.ndarray | None = None, night: bool = False,
                       wet: float = 0.0) -> IllusionContext:
    """The flat-road IllusionContext of a photo from its annotated lanes (left to right, pixels).

    image_size is (height, width). Pitch and yaw come from the lanes' vanishing point, the lateral
    offsets from back-projection; lane_width fixes the scale (camera height follows), or with
    lane_width=None camera_height does. lane_offsets holds the usable lanes only (too short ones are
    dropped), sorted left to right. Raises GroundPlaneError when the lanes give no ground plane, also
    when a lane lies outside the image (beyond LANE_X_MARGIN_FRAC / LANE_Y_MARGIN_FRAC, or with no point
    inside it), and ValueError when a lane has non-finite coordinates.
    """
    h, w = _check_size(image_size)
    wet = _check_wet(wet)
    sun = _sun(sun_direction, night)
    if lane_width is not None and not (isinstance(lane_width, (int, float, np.integer, np.floating))
                                       and 0.5 <= float(lane_width) <= 10.0):
        raise ValueError(f"lane_width: expected None or a width in [0.5, 10] metres, got {lane_width!r}")
    if lane_width is None and not (isinstance(camera_height, (int, float, np.integer, np.floating))
                                   and 0.2 <= float(camera_height) <= 20.0):
        raise ValueError(f"camera_height: expected a height in [0.2, 20] metres, got {camera_height!r}")
    if not isinstance(lanes, (list, tuple)):
        raise ValueError(f"lanes: expected a list of (N, 2) arrays, got {type(lanes).__name__}")
    usable = _usable_lanes(list(lanes), h, w)
    if len(usable) < 2:
        raise GroundPlaneError(
            f"lanes: need at least 2 usable lanes (>= {MIN_LANE_POINTS} points spanning >= "
            f"{MIN_LANE_SPAN_FRAC:.0%} of the image height) to find the vanishing point, got {len(usable)} of "
            f"{len(lanes)}; use fallback_context(image_size, ...) for an explicit default camera")
    (vp_u, vp_v), used = _vanishing_point(usable)

    probe = Camera(width=w, height=h, hfov_deg=float(hfov_deg))  # validates hfov; gives fx, cx, cy
    pitch = math.degrees(math.atan2(probe.cy - vp_v, probe.fy))
    if abs(pitch) > MAX_PITCH_DEG:
        raise GroundPlaneError(
            f"lanes: the vanishing point (row {vp_v:.1f}) implies a camera pitch of {pitch:.1f} deg, beyond "
            f"+-{MAX_PITCH_DEG:.0f} deg; use fallback_context(image_size, ...)")
    yaw = math.degrees(math.atan2((probe.cx - vp_u) * math.cos(math.radians(pitch)), probe.fx))
    if abs(yaw) > MAX_YAW_DEG:
        raise GroundPlaneError(
            f"lanes: the vanishing point (column {vp_u:.1f}) implies a camera yaw of {yaw:.1f} deg, beyond "
            f"+-{MAX_YAW_DEG:.0f} deg; use fallback_context(image_size, ...)")

    trial = Camera(width=w, height=h, hfov_deg=float(hfov_deg), height_m=_TRIAL_HEIGHT,
                   pitch_deg=pitch, yaw_deg=yaw)
    xs = []
    for pts in used:
        ground = trial.ground_intersect(pts[:, 0], pts[:, 1])
        x = ground[:, 0][np.isfinite(ground[:, 0])]
        if len(x) == 0:
            raise GroundPlaneError("lanes: a lane lies entirely above the recovered horizon; "
                                   "use fallback_context(image_size, ...)")
        xs.append(float(np.median(x)))
    xs = np.sort(np.asarray(xs))  # world x is perpendicular to the road direction (world z)
    spacing = float(np.median(np.diff(xs)))
    if spacing <= 1e-9:
        raise GroundPlaneError("lanes: two lanes back-project onto the same ground line; "
                               "use fallback_context(image_size, ...)")
    height_m = float(camera_height) if lane_width is None else _TRIAL_HEIGHT * float(lane_width) / spacing
    if not 0.2 <= height_m <= 20.0:
        raise GroundPlaneError(
            f"lanes: the lane spacing implies a camera height of {height_m:.2f} m, outside 0.2..20 m; "
            f"check lane_width / hfov_deg or use fallback_context(image_size, ...)")
    xs = xs * (height_m / _TRIAL_HEIGHT)
    center = 0.5 * (xs[0] + xs[-1])
    offsets = xs - center
    camera = Camera(width=w, height=h, hfov_deg=float(hfov_deg), height_m=height_m, pitch_deg=pitch, yaw_deg=yaw)
    return IllusionContext(camera=camera, road=_road(center, offsets), lane_offsets=tuple(float(d) for d in offsets),
                           sun_direction=sun, night=bool(night), wet=wet)


def fallback_context(image_size: tuple[int, int], camera_height: float = 1.5, hfov_deg: float = 90.0,
                     pitch_deg: float = 2.0, lane_width: float = 3.6, num_lanes: int = 4, yaw_deg: float = 0.0,
                     sun_direction: np.ndarray | None = None, night: bool = False,
                     wet: float = 0.0) -> IllusionContext:
    """An explicit default context when the lanes give no ground plane: a straight flat road of
    `num_lanes` lane lines (boundaries) spaced lane_width apart, the camera centred in the ego lane
    (the lane between lines (num_lanes-1)//2 and the next). image_size is (height, width)."""
    h, w = _check_size(image_size)
    wet = _check_wet(wet)
    sun = _sun(sun_direction, night)
    if not isinstance(num_lanes, (int, np.integer)) or isinstance(num_lanes, bool) or not 2 <= num_lanes <= 10:
        raise ValueError(f"num_lanes: expected an integer number of lane lines in [2, 10], got {num_lanes!r}")
    if not isinstance(lane_width, (int, float, np.integer, np.floating)) or not 0.5 <= float(lane_width) <= 10.0:
        raise ValueError(f"lane_width: expected a width in [0.5, 10] metres, got {lane_width!r}")
    camera = Camera(width=w, height=h, hfov_deg=float(hfov_deg), height_m=float(camera_height),
                    pitch_deg=float(pitch_deg), yaw_deg=float(yaw_deg))
    offsets = (np.arange(num_lanes) - (num_lanes - 1) / 2.0) * float(lane_width)
    ego = (num_lanes - 1) // 2
    center = -0.5 * (offsets[ego] + offsets[ego + 1])  # road centre x, so the camera (x = 0) is mid ego lane
    return IllusionContext(camera=camera, road=_road(center, offsets), lane_offsets=tuple(float(d) for d in offsets),
                           sun_direction=sun, night=bool(night), wet=wet)


__all__ = ["GroundPlaneError", "context_from_lanes", "fallback_context", "DAY_SUN_ELEV_AZIM_DEG",
           "NIGHT_SUN_ELEV_AZIM_DEG"]
