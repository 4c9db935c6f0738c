"""Reflection illusions: specular light on a wet road (sun glare, street-lamp and vehicle streaks).

A light source above a wet, slightly rough road is mirrored as a streak on the ground that runs
from below the source towards the camera (the image column under the source), brightest near the
mirror point where the camera sees the source's image. Each streak is laid out in world metres on
the road surface, projected like the road (so it narrows with distance) and screen-blended, so a
reflection only ever brightens the image; pixels off its footprint are left byte-identical.
Placement keeps level 1 in view: the first street lamp stands near (first_lamp_range_m), lamps go on
a road edge the camera sees, and mirrored vehicles drive in the lanes nearest the camera, the first
one close (distance_far_m of the level that introduced it).
"""

from __future__ import annotations

from typing import Callable

import cv2
import numpy as np

from lanevil_train.illusions import draw
from lanevil_train.illusions.context import IllusionContext
from lanevil_train.illusions.parameters import introduced, level_params

LEVELS: dict[str, list[dict]] = {
    # The sun low ahead: a glitter path on the asphalt around the mirror point of the sun.
    "sunlight_reflection": [
        dict(sun_elevation_deg=16.0, azimuth_max_deg=18.0, intensity=0.35, length_m=6.0, half_width_deg=2.5),
        dict(sun_elevation_deg=12.0, azimuth_max_deg=16.0, intensity=0.50, length_m=11.0, half_width_deg=4.0),
        dict(sun_elevation_deg=9.0, azimuth_max_deg=14.0, intensity=0.65, length_m=18.0, half_width_deg=6.0),
        dict(sun_elevation_deg=6.5, azimuth_max_deg=12.0, intensity=0.82, length_m=28.0, half_width_deg=8.5),
        dict(sun_elevation_deg=4.5, azimuth_max_deg=10.0, intensity=0.97, length_m=46.0, half_width_deg=11.5),
    ],
    # Street lamps over the road edges; each mirrored as a long lane-like streak.
    "streetlight_reflection": [
        dict(count=2, spacing_m=24.0, lamp_height_m=8.0, intensity=0.40, streak_length_frac=0.45,
             width_m=0.34, both_sides=0, first_lamp_range_m=8.0),
        dict(count=3, spacing_m=22.0, lamp_height_m=8.0, intensity=0.52, streak_length_frac=0.55,
             width_m=0.38, both_sides=0, first_lamp_range_m=10.0),
        dict(count=4, spacing_m=20.0, lamp_height_m=8.0, intensity=0.62, streak_length_frac=0.64,
             width_m=0.42, both_sides=1, first_lamp_range_m=14.0),
        dict(count=6, spacing_m=18.0, lamp_height_m=8.0, intensity=0.78, streak_length_frac=0.76,
             width_m=0.50, both_sides=1, first_lamp_range_m=18.0),
        dict(count=8, spacing_m=16.0, lamp_height_m=8.0, intensity=0.92, streak_length_frac=0.88,
             width_m=0.58, both_sides=1, first_lamp_range_m=16.0),
    ],
    # Vehicles ahead (tail lights, red) and oncoming (headlights, white) mirrored with their body colour.
    "vehicle_reflection": [
        dict(count=1, intensity=0.38, body_intensity=0.12, streak_length_frac=0.35, light_width_m=0.24,
             distance_far_m=17.0),
        dict(count=2, intensity=0.50, body_intensity=0.15, streak_length_frac=0.42, light_width_m=0.27,
             distance_far_m=28.0),
        dict(count=3, intensity=0.62, body_intensity=0.18, streak_length_frac=0.50, light_width_m=0.30,
             distance_far_m=45.0),
        dict(count=4, intensity=0.78, body_intensity=0.22, streak_length_frac=0.60, light_width_m=0.34,
             distance_far_m=45.0),
        dict(count=5, intensity=0.92, body_intensity=0.26, streak_length_frac=0.70, light_width_m=0.38,
             distance_far_m=45.0),
    ],
}

# the LEVELS keys that are whole numbers (int parameters of Illusion.parameters(); the others are floats)
INTEGER_KEYS = frozenset({"count", "both_sides"})

_WHITE_LAMP = np.array([1.0, 0.97, 0.90], np.float32)
_SODIUM_LAMP = np.array([1.0, 0.70, 0.30], np.float32)
_TAIL_LIGHT = np.array([1.0, 0.12, 0.08], np.float32)
_HEAD_LIGHT = np.array([1.0, 0.98, 0.92], np.float32)
_SUN = np.array([1.0, 0.96, 0.86], np.float32)
_BODY_COLOURS = np.array([[0.9, 0.9, 0.9], [0.75, 0.1, 0.1], [0.15, 0.25, 0.7], [0.6, 0.6, 0.62],
                          [0.9, 0.75, 0.2], [0.2, 0.5, 0.3]], np.float32)
Box = tuple[int, int, int, int]  # (y0, y1, x0, x1) pixel bounds
_SEGMENTS = 24   # quads along one streak (each filled with its own brightness)
SUN_FADE_M = 1.5  # metres over which the sun's glitter path fades in and out at its ends
DIST_NEAR_M = 12.0  # vehicles mirrored in vehicle_reflection stand at least this far ahead
_MAX_LIGHTS = 8  # rng draws are made for the most lights of any level, so levels share a layout


# ---------------------------------------------------------------------------------- geometry
def _streak(ctx: IllusionContext, layer: np.ndarray, base_xz: tuple[float, float], t_range: tuple[float, float],
            half_width_m: float, profile: Callable[[np.ndarray], np.ndarray], colour: np.ndarray,
            anchored: bool = True) -> Box | None:
    """Paint one streak into the (H, W, 3) float layer: the ground strip along the line from the
    camera's foot (t=0) to `base_xz` (t=1, under the source), over t in `t_range`, brightness
    `profile(t)` times `colour`; its half-width is `half_width_m` at t=1 and shrinks towards the camera
    in proportion to t, so the streak keeps a near-constant width in the image, as real ones do.
    A mirror image follows the viewer: in a clip frame the streak runs to the moved camera, from the
    source's place on the road (`anchored`) or, for the sun at infinity, from the same place relative to it."""
    if ctx.view is not None:
        if anchored:
            bx, bz = (float(v) for v in base_xz)  # reference world x, z of the ground under the source
            foot = ctx.view.to_current(np.array([bx, float(ctx.road.height(bz)), bz]))
            base_xz = (float(foot[0]), float(foot[2]))
        ctx = ctx.frame()
    bx, bz = base_xz
    t = np.linspace(t_range[0], t_range[1], _SEGMENTS + 1)
    z = np.maximum(t * bz, draw.NEAR_Z + 0.5)
    x = t * bx
    n = np.array([bz, -bx]) / max(np.hypot(bx, bz), 1e-9)  # horizontal normal of the streak
    hw = half_width_m * np.maximum(t, 0.05)
    side = np.stack([x[:, None] + np.array([-1.0, 1.0]) * hw[:, None] * n[0],
                     z[:, None] + np.array([-1.0, 1.0]) * hw[:, None] * n[1]], -1)  # (S+1, 2, 2)
    sz = np.maximum(side[..., 1], draw.NEAR_Z)
    pts = np.stack([side[..., 0], ctx.road.height(sz), sz], -1)
    pix, depth = draw.project(ctx, pts)
    values = profile(0.5 * (t[1:] + t[:-1]))
    drawn = []
    for i in range(_SEGMENTS):
        quad = np.array([pix[i, 0], pix[i + 1, 0], pix[i + 1, 1], pix[i, 1]])
        if values[i] <= 1e-3 or not np.all(np.isfinite(quad)) or np.any(depth[i:i + 2] <= 0):
            continue
        colour_v = tuple(float(c) for c in colour * values[i])
        cv2.fillPoly(layer, [np.round(quad * 16).astype(np.int32)], colour_v, lineType=cv2.LINE_AA, shift=4)
        drawn.append(quad)
    return _bounds(np.concatenate(drawn), layer.shape[:2], 0.0) if drawn else None


def _glow(ctx: IllusionContext, layer: np.ndarray, point: np.ndarray, radius_m: float, colour: np.ndarray,
          strength: float) -> Box | None:
    """A small round glow at a 3D light source (lamp head, vehicle light), sized by its distance."""
    pix, depth = draw.project(ctx, point[None])
    if depth[0] <= draw.NEAR_Z or not np.all(np.isfinite(pix)):
        return None
    r = max(1.0, radius_m * ctx.camera.fx / depth[0])
    h, w = ctx.image_size
    if not (-r <= pix[0, 0] <= w + r and -r <= pix[0, 1] <= h + r):
        return None
    centre = tuple(int(v) for v in np.round(pix[0] * 16))
    cv2.circle(layer, centre, int(round(r * 16)), tuple(float(c) * strength for c in colour), -1,
               lineType=cv2.LINE_AA, shift=4)
    return _bounds(pix, (h, w), r)


def _bounds(pix: np.ndarray, shape: tuple[int, int], pad: float) -> Box | None:
    """Pixel box (y0, y1, x0, x1) around points (K, 2) grown by `pad`, clipped to the image."""
    pts = pix[np.all(np.isfinite(pix), axis=1)]
    h, w = shape
    if pts.size == 0:
        return None
    x0, y0 = np.floor(pts.min(axis=0) - pad - 1).astype(int)
    x1, y1 = np.ceil(pts.max(axis=0) + pad + 2).astype(int)
    box = (max(0, y0), min(h, y1), max(0, x0), min(w, x1))
    return box if box[0] < box[1] and box[2] < box[3] else None


def _union(boxes: list, pad: int, shape: tuple[int, int]) -> Box | None:
    """The padded box covering all given boxes (None entries skipped), clipped to the image."""
    boxes = [b for b in boxes if b is not None]
    if not boxes:
        return None
    b = np.array(boxes)
    h, w = shape
    return (max(0, b[:, 0].min() - pad), min(h, b[:, 1].max() + pad),
            max(0, b[:, 2].min() - pad), min(w, b[:, 3].max() + pad))


def _finish(image: np.ndarray, ctx: IllusionContext, streaks: np.ndarray, streak_boxes: list,
            glows: np.ndarray | None, glow_boxes: list, blur_px: float, rng: np.random.Generator,
            glitter: float) -> np.ndarray:
    """Soften the streak layer, keep it on the asphalt, add glitter and (softened) glows, and
    screen-blend the result; all work is done inside the box that holds the drawn shapes."""
    out = image.copy()
    shape = ctx.image_size
    pad_s, pad_g = int(np.ceil(3 * blur_px)) + 1, int(np.ceil(3 * 0.004 * shape[1])) + 1
    sbox, gbox = _union(streak_boxes, pad_s, shape), _union(glow_boxes, pad_g, shape)
    box = _union([sbox, gbox], 0, shape)
    if box is None:
        return out
    y0, y1, x0, x1 = box
    layer = streaks[y0:y1, x0:x1]
    if sbox is not None:
        if blur_px > 0:
            layer = cv2.GaussianBlur(layer, (0, 0), sigmaX=blur_px * 0.6, sigmaY=blur_px)
        layer = layer * draw.road_mask(ctx, far=200.0)[y0:y1, x0:x1, None]
        if glitter > 0:  # wet-asphalt ripples: noise coarse across, fine along the image rows
            gh, gw = max(2, (y1 - y0) // 3), max(2, (x1 - x0) // 24)
            noise = rng.uniform(1.0 - glitter, 1.0 + glitter, size=(gh, gw)).astype(np.float32)
            layer = layer * cv2.resize(noise, (x1 - x0, y1 - y0), interpolation=cv2.INTER_LINEAR)[..., None]
    if gbox is not None and glows is not None:
        layer = layer + draw.soften(glows[y0:y1, x0:x1], 0.004 * shape[1])
    layer = np.clip(layer, 0.0, 1.0)
    src = image[y0:y1, x0:x1].astype(np.float32)
    res = src + (255.0 - src) * layer  # screen blend: brightens, never darkens
    out[y0:y1, x0:x1] = np.clip(np.floor(res + 0.5), 0, 255).astype(np.uint8)
    return out


def _check(image: np.ndarray, ctx: IllusionContext) -> None:
    """The image must be uint8 HxWx3 and match the context's size."""
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"reflection: image must be uint8 HxWx3, got {image.dtype} {image.shape}")
    if image.shape[:2] != ctx.image_size:
        raise ValueError(f"reflection: image size {image.shape[:2]} does not match context {ctx.image_size}")


def _bump(t_peak: float, sigma: float, floor: float, t_range: tuple[float, float],
          fade: float | None = None) -> Callable:
    """Brightness along a streak: a bump at the mirror point over a floor, faded at both ends (over
    `fade` in t, default 6 % of the streak)."""
    lo, hi = t_range
    fade = max(0.06 * (hi - lo) if fade is None else fade, 1e-6)

    def profile(t: np.ndarray) -> np.ndarray:
        body = floor + (1.0 - floor) * np.exp(-0.5 * ((t - t_peak) / sigma) ** 2)
        ends = np.clip((t - lo) / fade, 0, 1) * np.clip((hi - t) / fade, 0, 1)
        return body * ends
    return profile


# ---------------------------------------------------------------------------------- illusions
def render_sunlight_reflection(image: np.ndarray, ctx: IllusionContext, level: dict | int,
                               rng: np.random.Generator) -> np.ndarray:
    """Sun glare: a low sun ahead mirrored in the wet road as a bright glitter path that washes out
    the markings around the mirror point (distance camera_height / tan(elevation)). The path points
    towards the scene's own sun when that is low and ahead (sunset), else to a random azimuth."""
    _check(image, ctx)
    p = level_params(LEVELS["sunlight_reflection"], level)
    u = rng.uniform(-1.0, 1.0)
    az_max = p["azimuth_max_deg"]
    sx, sy, sz = (float(v) for v in ctx.sun_direction)
    if 0.0 < sy < np.sin(np.radians(25.0)) and sz > 0.0:  # a low sun ahead in the scene: glare under it
        az_deg = float(np.clip(np.degrees(np.arctan2(sx, sz)) + 0.25 * az_max * u, -40.0, 40.0))
    else:
        az_deg = az_max * u
    az = np.radians(az_deg)
    z_mirror = ctx.camera.height_m / np.tan(np.radians(p["sun_elevation_deg"]))
    # the path lies on the ground line from the camera towards the sun's azimuth, around the mirror point
    far = z_mirror + p["length_m"]
    near = max(z_mirror - 0.4 * p["length_m"], 1.5)
    base = (np.sin(az) * far, np.cos(az) * far)
    t_range = (near / far, 1.0)
    t_mirror = z_mirror / far
    h, w = ctx.image_size
    streaks = np.zeros((h, w, 3), np.float32)
    sigma = 0.3 * (1.0 - t_range[0]) + 0.04
    hw_far = far * np.tan(np.radians(p["half_width_deg"]))  # constant angular width, seen from the camera
    # wide soft halo, then the bright core
    fade = SUN_FADE_M / far  # the path fades in over the same metres at every level
    boxes = [_streak(ctx, streaks, base, t_range, hw_far, _bump(t_mirror, 1.5 * sigma, 0.35, t_range, fade),
                     _SUN * 0.6 * p["intensity"], anchored=False)]
    boxes += [_streak(ctx, streaks, base, t_range, 0.45 * hw_far, _bump(t_mirror, sigma, 0.2, t_range, fade),
                      np.minimum(_SUN * 1.4 * p["intensity"], 1.0), anchored=False)]
    return _finish(image, ctx, streaks, boxes, None, [], blur_px=0.012 * w, rng=rng, glitter=0.25)


def render_streetlight_reflection(image: np.ndarray, ctx: IllusionContext, level: dict | int,
                                  rng: np.random.Generator) -> np.ndarray:
    """Street-lamp streaks: lamps on arms over the road edge (white or sodium yellow), each mirrored
    as a long narrow streak running from under the lamp towards the camera, like a lane line."""
    _check(image, ctx)
    p = level_params(LEVELS["streetlight_reflection"], level)
    sodium = rng.random() < 0.5
    phase = rng.uniform(0.0, 1.0)
    arm = rng.uniform(0.8, 1.8, size=_MAX_LIGHTS)
    jitter = rng.uniform(-0.08, 0.08, size=_MAX_LIGHTS)
    first_right = draw.visible_side(ctx, 1 if rng.random() < 0.5 else -1,
                                    lambda sd: ctx.road.right_edge if sd > 0 else ctx.road.left_edge) > 0
    gain = 1.0 if ctx.night else 0.7
    colour = (_SODIUM_LAMP if sodium else _WHITE_LAMP) * p["intensity"] * gain
    h, w = ctx.image_size
    streaks = np.zeros((h, w, 3), np.float32)
    glows = np.zeros((h, w, 3), np.float32)
    lamps, boxes, glow_boxes = [], [], []
    for i in range(p["count"]):
        right = (i % 2 == 0) == first_right if p["both_sides"] else first_right
        k = i // 2 if p["both_sides"] else i
        # the first lamp (on each side) stands within first_lamp_range_m of 10 m ahead (a short range
        # at level 1, so even one faint streak is near and in view), the others spacing_m apart
        step = p["first_lamp_range_m"] * phase if k == 0 else (phase + k) * p["spacing_m"]
        z = 10.0 + step * (1.0 + jitter[i])
        d = ctx.road.right_edge - arm[i] if right else ctx.road.left_edge + arm[i]
        lamps.append((z, d))
    hc, hl = ctx.camera.height_m, p["lamp_height_m"]
    for z, d in sorted(lamps, reverse=True):  # far lamps first, near streaks drawn over them
        foot = ctx.road.world_point(d, z)
        base = (float(foot[0]), float(foot[2]))
        t_range = (1.0 - p["streak_length_frac"], 1.0)
        t_mirror = hc / (hc + hl)
        prof = _bump(t_mirror, 0.45, 0.45, t_range)
        boxes.append(_streak(ctx, streaks, base, t_range, 2.2 * p["width_m"], prof, colour * 0.3))
        boxes.append(_streak(ctx, streaks, base, t_range, p["width_m"], prof, colour))
        if ctx.night:  # the lit lamp head itself (by day the lamp is off and its head not drawn)
            glow_boxes.append(_glow(ctx, glows, foot + np.array([0.0, hl, 0.0]), 0.35,
                                    _SODIUM_LAMP if sodium else _WHITE_LAMP, 0.9))
    return _finish(image, ctx, streaks, boxes, glows, glow_boxes, blur_px=0.004 * w, rng=rng, glitter=0.3)


def render_vehicle_reflection(image: np.ndarray, ctx: IllusionContext, level: dict | int,
                              rng: np.random.Generator) -> np.ndarray:
    """Vehicle reflections: vehicles ahead mirrored in the wet road as a faint body-coloured patch
    and bright vertical streaks under their lights (red tail lights; white headlights if oncoming)."""
    _check(image, ctx)
    p = level_params(LEVELS["vehicle_reflection"], level)
    offsets = np.sort(np.asarray(ctx.lane_offsets, np.float64))
    centres = 0.5 * (offsets[1:] + offsets[:-1]) if len(offsets) >= 2 else np.array([0.0])
    # vehicles drive in the (up to) three lanes nearest the camera, which are in view
    near = np.argsort(np.abs(centres - ctx.road.lateral(0.0, 0.0)))[:3]
    lane_pick = near[rng.integers(0, len(near), size=_MAX_LIGHTS)]
    u_dist = rng.random(_MAX_LIGHTS)
    shift = rng.uniform(-0.4, 0.4, size=_MAX_LIGHTS)
    body = rng.integers(0, len(_BODY_COLOURS), size=_MAX_LIGHTS)
    oncoming = rng.random(_MAX_LIGHTS) < 0.3
    gain_light = 1.0 if ctx.night else 0.75
    gain_body = 0.5 if ctx.night else 1.0
    h, w = ctx.image_size
    streaks = np.zeros((h, w, 3), np.float32)
    glows = np.zeros((h, w, 3), np.float32)
    hc = ctx.camera.height_m
    boxes, glow_boxes = [], []
    # vehicles in random lanes and distances (they may overlap); far ones first, near ones drawn over.
    # A vehicle keeps the distance range of the level that introduced it: the first one is near.
    far = [introduced(LEVELS["vehicle_reflection"], "count", i, "distance_far_m", p) for i in range(p["count"])]
    dist = [DIST_NEAR_M + (f - DIST_NEAR_M) * u for f, u in zip(far, u_dist)]
    order = sorted(range(p["count"]), key=lambda i: -dist[i])
    for i in order:
        d, z = centres[lane_pick[i]] + shift[i], dist[i]
        light_h = 0.7 if oncoming[i] else 0.9
        light_c = _HEAD_LIGHT if oncoming[i] else _TAIL_LIGHT
        t_range = (1.0 - p["streak_length_frac"], 1.0)
        foot = ctx.road.world_point(d, z)
        prof_body = _bump(1.0, 0.5 * p["streak_length_frac"], 0.0, (t_range[0], 1.0))
        boxes.append(_streak(ctx, streaks, (float(foot[0]), float(foot[2])), (t_range[0], 1.0), 0.85,
                             prof_body, _BODY_COLOURS[body[i]] * p["body_intensity"] * gain_body))
        for side in (-0.7, 0.7):
            lp = ctx.road.world_point(d + side, z)
            prof = _bump(hc / (hc + light_h), 0.5, 0.5, t_range)
            boxes.append(_streak(ctx, streaks, (float(lp[0]), float(lp[2])), t_range, p["light_width_m"],
                                 prof, light_c * p["intensity"] * gain_light))
            if ctx.night:  # at night the lights themselves are seen, the unlit body is not
                src = lp + np.array([0.0, light_h, 0.0])
                glow_boxes.append(_glow(ctx, glows, src, 0.45, light_c, 0.3))  # halo, then the lamp
                glow_boxes.append(_glow(ctx, glows, src, 0.16, np.minimum(light_c + 0.5, 1.0), 1.0))
    return _finish(image, ctx, streaks, boxes, glows, glow_boxes, blur_px=0.004 * w, rng=rng, glitter=0.3)


RENDERERS: dict[str, Callable] = {
    "sunlight_reflection": render_sunlight_reflection,
    "streetlight_reflection": render_streetlight_reflection,
    "vehicle_reflection": render_vehicle_reflection,
}
