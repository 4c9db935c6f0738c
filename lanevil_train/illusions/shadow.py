"""Shadow illusions: 3D roadside objects cast shadows on the road along a chosen sun direction.

Each object (lamp pole with arm, fence slats, railing bars and posts, overhead wires) is a set of
segments at known heights above the road. A point h metres above road point (d, z) casts its shadow
at (d, z) + h * s, where s = -(sun horizontal direction) / tan(sun elevation) in the local road frame
(lateral d, forward z), i.e. the ray along -sun meets the road surface at the object's own height
profile. The ground shadow polygons are projected like the road (so they foreshorten and bend with
it), softened for the penumbra, and darken the image.

The light is the paper's (l, a): intensity -> `opacity` (how much light the shadow removes) and
`penumbra_px`; angle -> `sun_elevation_deg` and `sun_azimuth_deg` (0 = ahead along the road, 90 =
beside it, 180 = behind the camera), with the sun's side of the road drawn per seed (and swapped when
only the other road edge is in view). The scene's own sun is deliberately NOT used: every scene,
including a night one, gets the shadows of the level. At night (or when the road has unlit stretches)
darkening alone would not show, so the level's light is drawn too: a low floodlight
that lights a narrow pool around the object's shadow (the light between slats, bars and wires),
fading with distance, out of which the shadow is cut. By day a shadow only ever darkens.
Placement keeps level 1 in view: the lamp pole stands where its shadow crosses the road
`shadow_distance_m` ahead, the wires hang where their shadows fall ahead of the camera.
"""

from __future__ import annotations

import math
from typing import Callable

import cv2
import numpy as np

from lanevil_train.illusions import draw
from lanevil_train.illusions.context import IllusionContext
from lanevil_train.illusions.parameters import level_params

Z_FAR = 150.0      # metres: objects beyond this are not drawn (sub-pixel near the horizon anyway)
Z_BEHIND = -30.0   # metres: objects behind the camera still cast shadows forward into view
VERGE_M = 2.0      # shadows fall on the asphalt and this much of the verge on either side
SKY_TINT = (0.93, 0.97, 1.0)  # shadows are lit by the bluish sky: red loses a little more light
POOL_M = 0.2       # at night the level's light covers the ground this far around an object's shadow
POOL_BLUR = 0.004  # ... with a soft edge (Gaussian sigma as a fraction of the image height)
POOL_REACH_M = 30.0  # ... and fades with distance (to half at this many metres)
NIGHT_FLOOD = np.array([120.0, 115.0, 104.0], np.float32)  # RGB the floodlight adds per unit opacity (warm white)

LEVELS: dict[str, list[dict]] = {
    "streetlight_shadow": [
        {"sun_elevation_deg": 55, "sun_azimuth_deg": 40, "opacity": 0.25, "shadow_distance_m": 10.0,
         "pole_spacing_m": 30, "pole_height_m": 9.0, "arm_length_m": 2.5, "pole_width_m": 0.27, "penumbra_px": 3.0},
        {"sun_elevation_deg": 42, "sun_azimuth_deg": 40, "opacity": 0.35, "shadow_distance_m": 9.0,
         "pole_spacing_m": 30, "pole_height_m": 9.0, "arm_length_m": 2.5, "pole_width_m": 0.27, "penumbra_px": 2.5},
        {"sun_elevation_deg": 30, "sun_azimuth_deg": 40, "opacity": 0.45, "shadow_distance_m": 8.0,
         "pole_spacing_m": 30, "pole_height_m": 9.0, "arm_length_m": 2.5, "pole_width_m": 0.29, "penumbra_px": 2.0},
        {"sun_elevation_deg": 20, "sun_azimuth_deg": 40, "opacity": 0.55, "shadow_distance_m": 7.0,
         "pole_spacing_m": 30, "pole_height_m": 9.0, "arm_length_m": 2.5, "pole_width_m": 0.31, "penumbra_px": 1.5},
        {"sun_elevation_deg": 12, "sun_azimuth_deg": 40, "opacity": 0.65, "shadow_distance_m": 6.0,
         "pole_spacing_m": 30, "pole_height_m": 9.0, "arm_length_m": 2.5, "pole_width_m": 0.33, "penumbra_px": 1.5},
    ],
    "fence_shadow": [
        {"sun_elevation_deg": 50, "sun_azimuth_deg": 70, "opacity": 0.25, "fence_height_m": 1.4,
         "fence_length_m": 25, "slat_width_m": 0.10, "slat_gap_m": 0.14, "penumbra_px": 3.0},
        {"sun_elevation_deg": 38, "sun_azimuth_deg": 72, "opacity": 0.35, "fence_height_m": 1.6,
         "fence_length_m": 40, "slat_width_m": 0.11, "slat_gap_m": 0.13, "penumbra_px": 2.5},
        {"sun_elevation_deg": 27, "sun_azimuth_deg": 75, "opacity": 0.45, "fence_height_m": 1.8,
         "fence_length_m": 55, "slat_width_m": 0.12, "slat_gap_m": 0.12, "penumbra_px": 2.0},
        {"sun_elevation_deg": 18, "sun_azimuth_deg": 78, "opacity": 0.55, "fence_height_m": 2.0,
         "fence_length_m": 70, "slat_width_m": 0.13, "slat_gap_m": 0.11, "penumbra_px": 1.5},
        {"sun_elevation_deg": 11, "sun_azimuth_deg": 80, "opacity": 0.65, "fence_height_m": 2.2,
         "fence_length_m": 85, "slat_width_m": 0.14, "slat_gap_m": 0.10, "penumbra_px": 1.0},
    ],
    "rail_shadow": [
        {"sun_elevation_deg": 40, "sun_azimuth_deg": 80, "opacity": 0.25, "rail_height_m": 0.9,
         "bar_count": 2, "bar_thickness_m": 0.05, "post_spacing_m": 2.5, "rail_length_m": 60,
         "penumbra_px": 3.0},
        {"sun_elevation_deg": 28, "sun_azimuth_deg": 82, "opacity": 0.35, "rail_height_m": 1.0,
         "bar_count": 3, "bar_thickness_m": 0.06, "post_spacing_m": 2.5, "rail_length_m": 80,
         "penumbra_px": 2.5},
        {"sun_elevation_deg": 18, "sun_azimuth_deg": 84, "opacity": 0.45, "rail_height_m": 1.1,
         "bar_count": 4, "bar_thickness_m": 0.08, "post_spacing_m": 2.5, "rail_length_m": 100,
         "penumbra_px": 2.0},
        {"sun_elevation_deg": 12, "sun_azimuth_deg": 86, "opacity": 0.55, "rail_height_m": 1.2,
         "bar_count": 5, "bar_thickness_m": 0.10, "post_spacing_m": 2.5, "rail_length_m": 120,
         "penumbra_px": 1.5},
        {"sun_elevation_deg": 8, "sun_azimuth_deg": 88, "opacity": 0.65, "rail_height_m": 1.2,
         "bar_count": 6, "bar_thickness_m": 0.12, "post_spacing_m": 2.5, "rail_length_m": 140,
         "penumbra_px": 1.0},
    ],
    "wire_shadow": [
        {"sun_elevation_deg": 60, "sun_azimuth_deg": 60, "opacity": 0.30, "wire_height_m": 7.0,
         "along_wire_count": 1, "cross_wire_count": 1, "wire_spacing_m": 0.6,
         "shadow_width_m": 0.06, "sag_m": 0.4, "penumbra_px": 2.0},
        {"sun_elevation_deg": 50, "sun_azimuth_deg": 65, "opacity": 0.40, "wire_height_m": 7.0,
         "along_wire_count": 2, "cross_wire_count": 2, "wire_spacing_m": 0.6,
         "shadow_width_m": 0.08, "sag_m": 0.4, "penumbra_px": 1.7},
        {"sun_elevation_deg": 40, "sun_azimuth_deg": 70, "opacity": 0.50, "wire_height_m": 7.0,
         "along_wire_count": 3, "cross_wire_count": 3, "wire_spacing_m": 0.6,
         "shadow_width_m": 0.10, "sag_m": 0.4, "penumbra_px": 1.4},
        {"sun_elevation_deg": 32, "sun_azimuth_deg": 75, "opacity": 0.60, "wire_height_m": 7.0,
         "along_wire_count": 4, "cross_wire_count": 4, "wire_spacing_m": 0.6,
         "shadow_width_m": 0.12, "sag_m": 0.4, "penumbra_px": 1.1},
        {"sun_elevation_deg": 25, "sun_azimuth_deg": 80, "opacity": 0.70, "wire_height_m": 7.0,
         "along_wire_count": 6, "cross_wire_count": 6, "wire_spacing_m": 0.6,
         "shadow_width_m": 0.14, "sag_m": 0.4, "penumbra_px": 1.1},
    ],
}

# the LEVELS keys that are whole numbers (int parameters of Illusion.parameters(); the others are floats)
INTEGER_KEYS = frozenset({"bar_count", "along_wire_count", "cross_wire_count"})

# ---------------------------------------------------------------------------------------- geometry
def shadow_offset(elevation_deg: float, azimuth_deg: float, side: int) -> np.ndarray:
    """Ground displacement (dd, dz) of the shadow per metre of height, in the local road frame.

    The sun stands `azimuth_deg` from the road's forward axis, on side `side` (+1 right, -1 left).
    """
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    towards_sun = np.array([side * math.sin(az), math.cos(az)])
    return -towards_sun / math.tan(el)


def _fill_quads(ctx: IllusionContext, quads: np.ndarray, step: float = 1.0) -> np.ndarray:
    """Fill road-frame polygons (P, K, 2) of (d, z) into a float32 mask, each polygon on its own
    (cv2 fills a list of overlapping polygons with even-odd holes, so they are drawn one by one).

    Polygons reaching behind z = NEAR_Z (or the camera plane) are clipped; edges are densified every
    `step` metres (at most 48 pieces) so the shapes bend with curved or sloped roads."""
    h, w = ctx.image_size
    mask = np.zeros((h, w), np.float32)
    quads = np.asarray(quads, np.float64)
    if quads.size == 0:
        return mask
    if quads.ndim != 3 or quads.shape[2] != 2:
        raise ValueError(f"_fill_quads: expected polygons of shape (P, K, 2), got {quads.shape}")
    zmin, zmax = quads[:, :, 1].min(axis=1), quads[:, :, 1].max(axis=1)
    keep = (zmax > draw.NEAR_Z) & (zmin < Z_FAR)
    whole = quads[keep & (zmin >= draw.NEAR_Z)]
    pieces = list(quads[keep & (zmin < draw.NEAR_Z)])
    polys_px: list[np.ndarray] = []
    if len(whole):
        k = whole.shape[1]
        edges = np.roll(whole, -1, axis=1) - whole                       # (P, K, 2)
        n = int(np.clip(np.ceil(np.linalg.norm(edges, axis=2).max() / step), 1, 48))
        t = (np.arange(n) / n)[None, None, :, None]
        dense = (whole[:, :, None, :] + edges[:, :, None, :] * t).reshape(len(whole), k * n, 2)
        pix, depth = draw.project(ctx, draw.road_points(ctx, dense[..., 0], dense[..., 1]))
        in_front = np.all(depth > 0.5 * draw.NEAR_Z, axis=1)  # a yawed camera: some are partly behind it
        polys_px.extend(pix[in_front])
        pieces.extend(whole[~in_front])
    for piece in pieces:
        step_here = max(step, float(np.ptp(piece, axis=0).max()) / 48.0)
        pix = draw.project_ground_polygon(ctx, piece, step_here)
        if pix is not None:
            polys_px.append(pix)
    lim = float(2 ** 26)                                              # int32-safe in 1/16 pixels
    for poly in polys_px:
        if np.all(np.isfinite(poly)):
            fixed = np.clip(np.round(poly * 16.0), -lim, lim).astype(np.int32)
            cv2.fillPoly(mask, [fixed], 1.0, lineType=cv2.LINE_AA, shift=4)
    return mask


def _lifted_segment(p0: np.ndarray, p1: np.ndarray, h0: float, h1: float, s: np.ndarray) -> np.ndarray:
    """Shadow (4, 2) of a vertical strip whose bottom edge runs p0 -> p1 (road frame) at height h0
    and top edge at h1: the bottom edge shifted by h0 * s and the top edge by h1 * s."""
    return np.array([p0 + h0 * s, p1 + h0 * s, p1 + h1 * s, p0 + h1 * s])


def _strip(p0: np.ndarray, p1: np.ndarray, width: float) -> np.ndarray:
    """A ground strip (4, 2) of `width` metres centred on the segment p0 -> p1."""
    direction = (p1 - p0) / max(float(np.linalg.norm(p1 - p0)), 1e-9)
    normal = np.array([-direction[1], direction[0]]) * (width / 2.0)
    return np.array([p0 - normal, p1 - normal, p1 + normal, p0 + normal])


def _ground_band(ctx: IllusionContext) -> np.ndarray:
    """Mask of the asphalt plus VERGE_M on each side: where the shadows may fall."""
    return draw.road_mask(ctx, far=Z_FAR, margin=VERGE_M)


def _side_and_offset(level: dict, rng: np.random.Generator, ctx: IllusionContext | None = None,
                     gap: float = 0.0) -> tuple[int, np.ndarray]:
    """Sun side (+1 right / -1 left, drawn per seed) and the per-metre shadow offset (jittered).

    With `ctx`, the object stands `gap` metres outside the road edge on the sun's side, and that side
    is swapped when only the other road edge is in view (a wide road seen from its outer lane)."""
    side = int(rng.choice([-1, 1]))
    if ctx is not None:
        side = draw.visible_side(ctx, side, lambda sd: _edge_d(ctx, sd, gap))
    el = level["sun_elevation_deg"] * float(rng.uniform(0.95, 1.05))
    az = level["sun_azimuth_deg"] + float(rng.uniform(-4.0, 4.0))
    if rng.random() < 0.5:  # the sun behind the camera (shadows fall away) or ahead (towards us)
        az = 180.0 - az
    return side, shadow_offset(el, az, side)


def _edge_d(ctx: IllusionContext, side: int, gap: float) -> float:
    """Lateral offset `gap` metres outside the road edge on `side`."""
    return ctx.road.right_edge + gap if side > 0 else ctx.road.left_edge - gap


# ---------------------------------------------------------------------------------------- shapes
def _streetlight_quads(ctx: IllusionContext, lv: dict, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    side, s = _side_and_offset(lv, rng, ctx, 0.6)
    d0 = _edge_d(ctx, side, 0.6)
    spacing, height, arm, pw = lv["pole_spacing_m"], lv["pole_height_m"], lv["arm_length_m"], lv["pole_width_m"]
    quads, lit = [], []
    # one pole stands where its shadow crosses the road in front of the camera (or, if too short to
    # reach it, ends) shadow_distance_m ahead, whether the sun is behind or ahead; the rest are
    # spaced out from it along the road
    d_mid = float(np.clip(ctx.road.lateral(0.0, 0.0), ctx.road.left_edge, ctx.road.right_edge))
    h_ref = float(np.clip((d_mid - d0) / s[0], 0.0, height)) if abs(s[0]) > 1e-9 else height
    z_key = lv["shadow_distance_m"] * float(rng.uniform(0.9, 1.1)) - h_ref * s[1]
    for z in z_key + spacing * np.arange(math.floor((Z_BEHIND - z_key) / spacing), (Z_FAR - z_key) / spacing):
        base = np.array([d0, z])
        quads.append(_lifted_segment(base - [0, pw / 2], base + [0, pw / 2], 0.0, height, s))      # pole
        tip = base + np.array([-side * arm, 0.0])
        quads.append(_lifted_segment(base, tip, height - 0.12, height + 0.04, s))                # arm
        head0, head1 = tip + np.array([side * 0.15, 0.0]), tip - np.array([side * 0.55, 0.0])
        quads.append(np.array([head0 + (height - 0.25) * s + [0, -0.2], head1 + (height - 0.25) * s + [0, -0.2],
                               head1 + (height - 0.25) * s + [0, 0.2], head0 + (height - 0.25) * s + [0, 0.2]]))
        lit.append(_lifted_segment(base - [0, pw / 2 + 2 * POOL_M], base + [0, pw / 2 + 2 * POOL_M], 0.0, height, s))
        lit.append(_lifted_segment(base + [side * POOL_M, 0], tip - [side * (0.55 + POOL_M), 0],
                                   height - POOL_M, height, s))
    return np.array(quads), np.array(lit)


def _fence_quads(ctx: IllusionContext, lv: dict, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    side, s = _side_and_offset(lv, rng, ctx, 0.5)
    d0 = _edge_d(ctx, side, 0.5)
    height, sw, pitch = lv["fence_height_m"], lv["slat_width_m"], lv["slat_width_m"] + lv["slat_gap_m"]
    start = float(rng.uniform(-10.0, 15.0))
    zs = np.arange(start, start + lv["fence_length_m"], pitch)
    heights = height * (1.0 + rng.uniform(-0.03, 0.03, len(zs)))      # slightly uneven slat tops
    quads = [_lifted_segment(np.array([d0, z]), np.array([d0, z + sw]), 0.0, hz, s) for z, hz in zip(zs, heights)]
    p0, p1 = np.array([d0, start]), np.array([d0, start + lv["fence_length_m"]])
    for h in (0.3, height - 0.3):                                      # the two horizontal rails
        quads.append(_lifted_segment(p0, p1, h - 0.05, h + 0.05, s))
    return np.array(quads), _lifted_segment(p0, p1, 0.0, height, s)[None]


def _rail_quads(ctx: IllusionContext, lv: dict, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    side, s = _side_and_offset(lv, rng, ctx, 0.3)
    d0 = _edge_d(ctx, side, 0.3)
    start = float(rng.uniform(-20.0, 0.0))
    p0, p1 = np.array([d0, start]), np.array([d0, start + lv["rail_length_m"]])
    top, t, n = lv["rail_height_m"], lv["bar_thickness_m"], lv["bar_count"]
    quads = [_lifted_segment(p0, p1, h - t / 2, h + t / 2, s) for h in np.linspace(0.25, top, n)]
    for z in np.arange(start, start + lv["rail_length_m"], lv["post_spacing_m"]):
        quads.append(_lifted_segment(np.array([d0, z]), np.array([d0, z + 0.08]), 0.0, top + t / 2, s))
    return np.array(quads), _lifted_segment(p0, p1, 0.0, top + t / 2, s)[None]


def _wire_quads(ctx: IllusionContext, lv: dict, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    side, s = _side_and_offset(lv, rng)
    height, width, sag = lv["wire_height_m"], lv["shadow_width_m"], lv["sag_m"]
    quads, lit = [], []
    span = 40.0
    n_max = max(lv["along_wire_count"] for lv in LEVELS["wire_shadow"])  # draw for the most wires, use
    m_max = max(lv["cross_wire_count"] for lv in LEVELS["wire_shadow"])  # the first n: levels nest
    # the wires hang wherever their shadows land on the asphalt ahead of the camera (within 4 m of
    # its lateral position, so in view), beside or above the road
    d_cam = float(ctx.road.lateral(0.0, 0.0))
    lo = max(ctx.road.left_edge + 1.5, d_cam - 4.0)
    hi = max(lo, min(ctx.road.right_edge - 1.5, d_cam + 4.0))
    target = float(rng.uniform(lo, hi))
    z0s = rng.uniform(-span, 0.0, n_max)
    cross = rng.uniform([5.0, -0.6, -1.0], [60.0, 0.6, 1.0], size=(m_max, 3))
    for i in range(lv["along_wire_count"]):          # wires along the road, sagging between poles
        h = height - 0.25 * i
        d = target - h * s[0] + (i // 2 + 1) * (1 if i % 2 else -1) * lv["wire_spacing_m"] * (i > 0)
        zs = np.linspace(z0s[i], Z_FAR, int((Z_FAR - z0s[i]) / 2.0) + 1)
        frac = ((zs - z0s[i]) % span) / span
        hz = h - sag * 4.0 * frac * (1.0 - frac)
        pts = np.stack([np.full_like(zs, d), zs], 1) + hz[:, None] * s
        quads.extend(_strip(a, b, width) for a, b in zip(pts[:-1], pts[1:]))
        lit.extend(_strip(a, b, width + 2.0 * POOL_M) for a, b in zip(pts[:-1], pts[1:]))
    left, right = ctx.road.left_edge - 3.0, ctx.road.right_edge + 3.0
    for zc, slant, dh in cross[:lv["cross_wire_count"]]:   # wires crossing the road, at a slant
        ds = np.linspace(left, right, 9)
        frac = (ds - left) / (right - left)
        hz = height + dh - sag * 4.0 * frac * (1.0 - frac)
        # hung so that its shadow crosses the road zc metres ahead at every sun angle (levels nest)
        pts = np.stack([ds, zc - (height + dh) * s[1] + slant * (ds - left)], 1) + hz[:, None] * s
        quads.extend(_strip(a, b, width) for a, b in zip(pts[:-1], pts[1:]))
        lit.extend(_strip(a, b, width + 2.0 * POOL_M) for a, b in zip(pts[:-1], pts[1:]))
    return np.array(quads), np.array(lit)


_SHAPES = {"streetlight_shadow": _streetlight_quads, "fence_shadow": _fence_quads,
           "rail_shadow": _rail_quads, "wire_shadow": _wire_quads}


# ---------------------------------------------------------------------------------------- rendering
def _geometry(name: str, ctx: IllusionContext, level: dict | int,
              rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Shadow coverage mask (0..1, exactly 0 off the footprint) and the light-pool polygons."""
    lv = level_params(LEVELS[name], level)
    quads, lit = _SHAPES[name](ctx, lv, rng)
    scale = ctx.image_size[1] / 1280.0
    mask = draw.soften(_fill_quads(ctx, quads), lv["penumbra_px"] * scale) * _ground_band(ctx)
    mask[mask < 1e-3] = 0.0                    # no invisible far tails of the blur
    return np.clip(mask, 0.0, 1.0), lit


def _pool(ctx: IllusionContext, lit: np.ndarray) -> np.ndarray:
    """Soft ground pool (0..1) of the level's light, fading with distance like headlights."""
    reach = 1.0 / (1.0 + np.square(draw.row_distance(ctx) / POOL_REACH_M))
    pool = draw.soften(_fill_quads(ctx, lit), POOL_BLUR * ctx.image_size[0]) * _ground_band(ctx)
    return np.clip(pool * reach[:, None].astype(np.float32), 0.0, 1.0)


def shadow_mask(name: str, ctx: IllusionContext, level: dict | int, rng: np.random.Generator) -> np.ndarray:
    """The float32 shadow coverage (0..1) of illusion `name` at `level` (a point, or a severity 1..5): exactly 0
    off its footprint.

    Consumes `rng` exactly as the render function does, so the same seed gives the same mask.
    """
    return _geometry(name, ctx, level, rng)[0]


def light_pool(name: str, ctx: IllusionContext, level: dict | int, rng: np.random.Generator) -> np.ndarray:
    """The soft ground pool (0..1) the level's own light covers around its shadow (used at night)."""
    return _pool(ctx, _geometry(name, ctx, level, rng)[1])


def _render(name: str, image: np.ndarray, ctx: IllusionContext, level: dict | int,
            rng: np.random.Generator) -> np.ndarray:
    level = level_params(LEVELS[name], level)
    mask, lit = _geometry(name, ctx, level, rng)
    out = draw.shade(image, mask, [(1.0 - level["opacity"]) * c for c in SKY_TINT])
    if not (ctx.night or draw.RoadLight(image, ctx).road_is_dark()):
        return out
    # at night (or on a photo whose road has unlit stretches) the shadow is cut out of the level's own
    # light: a low floodlight that lights the ground just around the object's shadow (the light
    # between slats, bars and wires), so the shadow shows where the scene itself is dark
    flood = NIGHT_FLOOD * level["opacity"]
    light = (_pool(ctx, lit) * (1.0 - mask))[..., None] * flood.reshape(1, 1, 3)
    return np.clip(out.astype(np.float32) + light + 0.5, 0, 255).astype(np.uint8)


def render_streetlight_shadow(image: np.ndarray, ctx: IllusionContext, level: dict | int,
                              rng: np.random.Generator) -> np.ndarray:
    """Shadows of lamp poles with arms beside the road, long and slanting at low sun."""
    return _render("streetlight_shadow", image, ctx, level, rng)


def render_fence_shadow(image: np.ndarray, ctx: IllusionContext, level: dict | int,
                        rng: np.random.Generator) -> np.ndarray:
    """A comb of slat shadows from a roadside fence reaching across the lanes."""
    return _render("fence_shadow", image, ctx, level, rng)


def render_rail_shadow(image: np.ndarray, ctx: IllusionContext, level: dict | int,
                       rng: np.random.Generator) -> np.ndarray:
    """Railing-bar shadows at low side sun: dark and bright lines parallel to the lanes."""
    return _render("rail_shadow", image, ctx, level, rng)


def render_wire_shadow(image: np.ndarray, ctx: IllusionContext, level: dict | int,
                       rng: np.random.Generator) -> np.ndarray:
    """Thin shadows of overhead wires running along and across the road."""
    return _render("wire_shadow", image, ctx, level, rng)


RENDERERS: dict[str, Callable] = {
    "streetlight_shadow": render_streetlight_shadow,
    "fence_shadow": render_fence_shadow,
    "rail_shadow": render_rail_shadow,
    "wire_shadow": render_wire_shadow,
}
