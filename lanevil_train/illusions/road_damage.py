"""Road-damage illusions: cracks, sealed repairs, skid marks painted into the asphalt; guard rails.

Everything is placed in road coordinates (d lateral, z forward metres) or as 3D world geometry and
projected with the scene camera, so damage foreshortens like the road. Surface damage darkens the
asphalt multiplicatively (it keeps the road's own texture and lighting, by day and by night) and is
clipped to the road mask; the guard rail is an opaque 3D object drawn far to near.
Randomness: each render draws the layout for the most severe level (the upper bounds of the
illusion's parameters) and keeps the first `count` items, so a higher severity contains the damage of a
lower one (same seed); an item is placed by the rules of the level that introduced it (level 1's few
cracks, patch and skid pair lie near the camera; a point's own z_far caps them: parameters.introduced)
and keeps its place while higher levels enlarge it. Each item draws several candidate places and takes
the first one in view and lit (`draw.RoadLight.pick`): by day the plain random place, at night one in
the headlights or under a lamp, where a darkening of the asphalt can be seen at all.
"""

from __future__ import annotations

from typing import Callable

import cv2
import numpy as np

from lanevil_train.illusions import draw
from lanevil_train.illusions.context import IllusionContext
from lanevil_train.illusions.parameters import introduced, level_params

Z_NEAR = 3.0    # metres: surface damage starts here
Z_FAR = 45.0    # and ends here (beyond it, it is sub-pixel)
RAIL_Z_FAR = 120.0  # metres: guard rails run from z_start_m to here
CANDIDATES = 16  # places drawn per damage item; the first lit one is used (RoadLight.pick)
_AA = cv2.LINE_AA
_SHIFT = 4

LEVELS: dict[str, list[dict]] = {
    "road_crack": [
        dict(crack_count=14, crack_length_m=2.5, crack_width_m=0.012, branch_prob=0.2, alligator_patches=0,
             shade_factor=0.62, z_far_m=15.0),
        dict(crack_count=17, crack_length_m=3.0, crack_width_m=0.014, branch_prob=0.3, alligator_patches=0,
             shade_factor=0.58, z_far_m=18.0),
        dict(crack_count=20, crack_length_m=3.5, crack_width_m=0.017, branch_prob=0.45, alligator_patches=1,
             shade_factor=0.53, z_far_m=32.0),
        dict(crack_count=26, crack_length_m=4.0, crack_width_m=0.020, branch_prob=0.6, alligator_patches=2,
             shade_factor=0.48, z_far_m=45.0),
        dict(crack_count=40, crack_length_m=5.0, crack_width_m=0.025, branch_prob=0.8, alligator_patches=4,
             shade_factor=0.42, z_far_m=45.0),
    ],
    "road_repair": [
        dict(strip_count=1, strip_length_m=12.0, strip_width_m=0.15, strip_offset_from_line_m=1.2,
             patch_count=1, patch_length_m=2.0, tar_shade_factor=0.72, gloss_factor=1.00, patch_z_far_m=10.0),
        dict(strip_count=1, strip_length_m=14.0, strip_width_m=0.17, strip_offset_from_line_m=1.0,
             patch_count=1, patch_length_m=2.2, tar_shade_factor=0.65, gloss_factor=1.05, patch_z_far_m=10.0),
        dict(strip_count=1, strip_length_m=20.0, strip_width_m=0.20, strip_offset_from_line_m=0.8,
             patch_count=2, patch_length_m=2.4, tar_shade_factor=0.58, gloss_factor=1.10, patch_z_far_m=14.0),
        dict(strip_count=2, strip_length_m=28.0, strip_width_m=0.24, strip_offset_from_line_m=0.6,
             patch_count=2, patch_length_m=2.5, tar_shade_factor=0.50, gloss_factor=1.15, patch_z_far_m=16.0),
        dict(strip_count=3, strip_length_m=36.0, strip_width_m=0.28, strip_offset_from_line_m=0.45,
             patch_count=3, patch_length_m=3.0, tar_shade_factor=0.44, gloss_factor=1.20, patch_z_far_m=16.0),
    ],
    "tire_marks": [
        dict(pair_count=1, mark_length_m=13.0, lateral_sweep_m=0.5, tire_width_m=0.22, track_width_m=1.6,
             shade_factor=0.70, start_z_far_m=8.0),
        dict(pair_count=1, mark_length_m=15.0, lateral_sweep_m=1.2, tire_width_m=0.22, track_width_m=1.6,
             shade_factor=0.64, start_z_far_m=10.0),
        dict(pair_count=2, mark_length_m=17.0, lateral_sweep_m=2.0, tire_width_m=0.22, track_width_m=1.6,
             shade_factor=0.58, start_z_far_m=12.0),
        dict(pair_count=3, mark_length_m=20.0, lateral_sweep_m=3.0, tire_width_m=0.22, track_width_m=1.6,
             shade_factor=0.52, start_z_far_m=14.0),
        dict(pair_count=4, mark_length_m=25.0, lateral_sweep_m=4.0, tire_width_m=0.24, track_width_m=1.6,
             shade_factor=0.45, start_z_far_m=14.0),
    ],
    "guard_rail": [
        dict(sides=1, offset_from_edge_line_m=2.0, z_start_m=11.0, post_spacing_m=4.0, beam_height_m=0.70,
             beam_depth_m=0.31, post_height_m=0.80),
        dict(sides=1, offset_from_edge_line_m=1.6, z_start_m=9.0, post_spacing_m=3.5, beam_height_m=0.70,
             beam_depth_m=0.31, post_height_m=0.80),
        dict(sides=1, offset_from_edge_line_m=0.9, z_start_m=6.0, post_spacing_m=3.0, beam_height_m=0.70,
             beam_depth_m=0.31, post_height_m=0.80),
        dict(sides=2, offset_from_edge_line_m=0.4, z_start_m=4.0, post_spacing_m=2.5, beam_height_m=0.70,
             beam_depth_m=0.31, post_height_m=0.80),
        dict(sides=2, offset_from_edge_line_m=0.0, z_start_m=2.5, post_spacing_m=2.0, beam_height_m=0.70,
             beam_depth_m=0.31, post_height_m=0.80),
    ],
}

# the LEVELS keys that are whole numbers (int parameters of Illusion.parameters(); the others are floats)
INTEGER_KEYS = frozenset({"crack_count", "alligator_patches", "strip_count", "patch_count", "pair_count", "sides"})

# ---------------------------------------------------------------------------------------- helpers
def _noise(shape: tuple[int, int], rng: np.random.Generator, cell_px: float) -> np.ndarray:
    """Smooth value noise in [0, 1] of `shape` (texture for worn, uneven surfaces)."""
    h, w = shape
    small = rng.random((max(2, int(h / cell_px)), max(2, int(w / cell_px)))).astype(np.float32)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)


def _darken_road(image: np.ndarray, ctx: IllusionContext, layers: list[tuple[np.ndarray, float, float, float]],
                rng: np.random.Generator) -> np.ndarray:
    """Apply damage layers (mask, shade factor, blur px, texture 0..1) to the asphalt only.

    Each mask is blurred, clipped to the road mask and modulated by smooth noise (uneven wear),
    and the image is multiplied by the product of the layers' gains. Work is done in the bounding
    box of the masks; outside every mask the image is returned byte-identical.
    """
    h, w = ctx.image_size
    out = image.copy()
    any_mask = np.zeros((h, w), np.uint8)
    for mask, *_ in layers:
        any_mask |= (mask > 0).astype(np.uint8)
    x, y, bw, bh = cv2.boundingRect(any_mask)
    if bw == 0 or bh == 0:
        return out
    pad = int(4 * max(blur for _, _, blur, _ in layers)) + 2
    x0, y0, x1, y1 = max(0, x - pad), max(0, y - pad), min(w, x + bw + pad), min(h, y + bh + pad)
    crop = (slice(y0, y1), slice(x0, x1))
    road = draw.road_mask(ctx)[crop]
    noise = _noise((y1 - y0, x1 - x0), rng, 10.0)
    gain = np.ones((y1 - y0, x1 - x0), np.float32)
    for mask, factor, blur, texture in layers:
        m = draw.soften(np.ascontiguousarray(mask[crop]), blur) * road
        if texture > 0:
            m *= (1.0 - texture) + texture * noise
        gain *= 1.0 + np.clip(m, 0.0, 1.0) * (float(factor) - 1.0)
    out[crop] = np.clip(image[crop].astype(np.float32) * gain[..., None] + 0.5, 0, 255).astype(np.uint8)
    return out


def _walk(rng: np.random.Generator, start: np.ndarray, heading: float, length: float,
          jitter: float = 0.35) -> np.ndarray:
    """A jagged random-walk polyline (N, 2) of (d, z) from `start`, `length` metres long."""
    n = max(3, int(length / 0.15))
    steps = rng.uniform(0.08, 0.22, n)
    # slow wander of the direction plus an uncorrelated zig-zag per step (jagged, not smooth)
    theta = heading + np.cumsum(rng.normal(0.0, jitter, n)) * 0.25 + rng.normal(0.0, 0.55, n)
    delta = np.stack([np.cos(theta), np.sin(theta)], 1) * steps[:, None]
    pts = start[None, :] + np.concatenate([np.zeros((1, 2)), np.cumsum(delta, 0)])
    return pts[np.cumsum(np.r_[0.0, steps]) <= length]


def _draw_ground_lines(ctx: IllusionContext, lines: list[np.ndarray], width_m: float) -> np.ndarray:
    """Draw road polylines (d, z) of physical width `width_m` into a float32 mask.

    Each polyline is projected, cut into short chunks, and drawn with a pixel thickness from its
    depth; sub-pixel widths are drawn 1 px wide with proportionally lower intensity (hairlines).
    """
    h, w = ctx.image_size
    lines = [ln for ln in lines if len(ln) >= 2]
    mask = np.zeros((h, w), np.uint8)
    if not lines:
        return mask.astype(np.float32)
    pts = np.concatenate(lines)
    pix, depth = draw.project(ctx, draw.road_points(ctx, pts[:, 0], np.maximum(pts[:, 1], draw.NEAR_Z)))
    width_px = width_m * ctx.camera.fx / np.maximum(depth, 1e-6)
    ipix = np.round(pix * (1 << _SHIFT))
    ends = np.cumsum([len(ln) for ln in lines])
    buckets: dict[tuple[int, int], list[np.ndarray]] = {}
    for start, end in zip(np.r_[0, ends[:-1]], ends):
        for a in range(start, end - 1, 6):
            sl = slice(a, min(a + 7, end))
            if not np.all(np.isfinite(ipix[sl])) or np.any(depth[sl] <= 0):
                continue
            wpx = float(width_px[sl].mean())
            level = int(round(255 * min(1.0, wpx) ** 0.7))
            if level > 0:
                buckets.setdefault((max(1, int(round(wpx))), level), []).append(ipix[sl].astype(np.int32))
    for (thick, level), polys in sorted(buckets.items(), key=lambda kv: kv[0][1]):
        cv2.polylines(mask, polys, False, level, thick, _AA, _SHIFT)
    return mask.astype(np.float32) * (1.0 / 255.0)


def _ribbon(line: np.ndarray, width: float) -> np.ndarray:
    """Closed polygon (2N, 2) of a strip `width` metres wide around a (d, z) polyline."""
    t = np.gradient(line, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-9)
    n = np.stack([t[:, 1], -t[:, 0]], 1) * (width / 2.0)
    return np.concatenate([line + n, (line - n)[::-1]])


def _road_span(ctx: IllusionContext, margin: float = 0.3) -> tuple[float, float]:
    """Lateral range (d) of the asphalt, shrunk by `margin`."""
    return ctx.road.left_edge + margin, ctx.road.right_edge - margin


# ---------------------------------------------------------------------------------------- illusions
def render_road_crack(image: np.ndarray, ctx: IllusionContext, level: dict | int,
                      rng: np.random.Generator) -> np.ndarray:
    """Dark, thin, slightly blurred crack network: hairline cracks (1) to alligator cracking (5)."""
    p = level_params(LEVELS["road_crack"], level)
    top = LEVELS["road_crack"][-1]
    lo, hi = _road_span(ctx)
    lines: list[np.ndarray] = []
    light = draw.RoadLight(image, ctx)
    crack_rngs = [np.random.default_rng(s) for s in rng.integers(0, 2**63, top["crack_count"])]
    for i, crng in enumerate(crack_rngs[:p["crack_count"]]):
        z_far = introduced(LEVELS["road_crack"], "crack_count", i, "z_far_m", p)
        ds, zs = crng.uniform(lo, hi, CANDIDATES), Z_NEAR + (z_far - Z_NEAR) * crng.random(CANDIDATES) ** 1.5
        k = light.pick(ds, zs)
        start = np.array([ds[k], zs[k]])
        longitudinal = crng.random() < 0.5
        heading = np.pi / 2 if longitudinal else (0.0 if crng.random() < 0.5 else np.pi)
        heading += crng.normal(0.0, 0.25)
        main = _walk(crng, start, heading, p["crack_length_m"] * crng.uniform(0.6, 1.2))
        lines.append(main)
        for _ in range(3):  # branches off the main crack
            if crng.random() < p["branch_prob"] and len(main) > 3:
                i = int(crng.integers(1, len(main) - 1))
                turn = crng.choice([-1.0, 1.0]) * crng.uniform(0.5, 1.2)
                lines.append(_walk(crng, main[i], heading + turn, p["crack_length_m"] * crng.uniform(0.2, 0.5)))
    patch_rngs = [np.random.default_rng(s) for s in rng.integers(0, 2**63, top["alligator_patches"])]
    for prng in patch_rngs[:p["alligator_patches"]]:
        lines += _alligator(prng, lo, hi, light)
    mask = _draw_ground_lines(ctx, lines, p["crack_width_m"])
    return _darken_road(image, ctx, [(mask, p["shade_factor"], 0.5, 0.25)], rng)


def _alligator(rng: np.random.Generator, lo: float, hi: float, light: draw.RoadLight) -> list[np.ndarray]:
    """Interconnected cracking: a jittered grid of nodes joined by jagged edges, in one (lit) patch."""
    pw, pl, cell = rng.uniform(1.8, 3.2), rng.uniform(3.0, 6.0), rng.uniform(0.4, 0.6)
    ds, zs = rng.uniform(lo, max(lo, hi - pw), CANDIDATES), rng.uniform(Z_NEAR + 1.0, 15.0, CANDIDATES)
    k = light.pick(ds + pw / 2, zs + pl / 2)
    d0, z0 = ds[k], zs[k]
    nd, nz = int(pw / cell) + 1, int(pl / cell) + 1
    gd, gz = np.meshgrid(np.arange(nd) * cell, np.arange(nz) * cell)
    nodes = np.stack([gd + d0, gz + z0], -1) + rng.uniform(-0.45, 0.45, (nz, nd, 2)) * cell
    keep = rng.random((nz, nd, 2)) < 0.85  # some edges missing: cells merge
    lines = []
    for i in range(nz):
        for j in range(nd):
            for k, (di, dj) in enumerate(((0, 1), (1, 0))):
                if i + di < nz and j + dj < nd and keep[i, j, k]:
                    a, b = nodes[i, j], nodes[i + di, j + dj]
                    mid = (a + b) / 2 + rng.normal(0.0, 0.08, 2) * cell / 0.4
                    lines.append(np.stack([a, (a + mid) / 2, mid, (mid + b) / 2, b]))
    return lines


def render_road_repair(image: np.ndarray, ctx: IllusionContext, level: dict | int,
                       rng: np.random.Generator) -> np.ndarray:
    """Sealed repairs: glossy dark tar strips (lane-like, parallel to the lanes) and transverse patches."""
    p = level_params(LEVELS["road_repair"], level)
    top = LEVELS["road_repair"][-1]
    h, w = ctx.image_size
    lo, hi = _road_span(ctx)
    tar: list[np.ndarray] = []
    sheen: list[np.ndarray] = []
    patches: list[np.ndarray] = []
    lanes = np.asarray(ctx.lane_offsets if ctx.lane_offsets else (0.0,), np.float64)
    light = draw.RoadLight(image, ctx)
    d_cam = float(ctx.road.lateral(0.0, 0.0))
    strip_rngs = [np.random.default_rng(s) for s in rng.integers(0, 2**63, top["strip_count"])]
    for srng in strip_rngs[:p["strip_count"]]:
        line_d = np.resize(srng.permutation(lanes), CANDIDATES)  # every line is a candidate
        side = srng.choice([-1.0, 1.0], CANDIDATES)
        z0s = srng.uniform(Z_NEAR, 10.0, CANDIDATES)
        k = light.pick(line_d, z0s + 2.0)  # beside a line in view (and lit) from near its start
        d, z0 = float(np.clip(line_d[k] + side[k] * p["strip_offset_from_line_m"], lo, hi)), float(z0s[k])
        zs = np.linspace(z0, min(z0 + p["strip_length_m"], Z_FAR + 5.0), 60)
        ds = d + np.cumsum(srng.normal(0.0, 0.012, len(zs)))  # follows a meandering longitudinal crack
        line = np.stack([ds, zs], 1)
        tar.append(_ribbon(line, p["strip_width_m"]))
        sheen.append(_ribbon(line, p["strip_width_m"] * 0.3))
    patch_rngs = [np.random.default_rng(s) for s in rng.integers(0, 2**63, top["patch_count"])]
    for i, prng in enumerate(patch_rngs[:p["patch_count"]]):
        width = prng.uniform(1.5, 3.5)
        z_far = introduced(LEVELS["road_repair"], "patch_count", i, "patch_z_far_m", p)
        z0s = prng.uniform(Z_NEAR + 1.0, z_far, CANDIDATES)
        # centred within the view ahead (|lateral| < 0.8 z from the camera), on the asphalt
        d0s = np.clip(d_cam + prng.uniform(-0.8, 0.8, CANDIDATES) * z0s - width / 2, lo, max(lo, hi - width))
        k = light.pick(d0s + width / 2, z0s + 1.0)
        d0, z0 = float(d0s[k]), float(z0s[k])
        skew = prng.normal(0.0, 0.15)
        length = p["patch_length_m"] * prng.uniform(0.8, 1.2)
        rect = np.array([[d0, z0], [d0 + width, z0 + skew], [d0 + width, z0 + skew + length], [d0, z0 + length]])
        patches.append(rect)
        edges = np.concatenate([rect, rect[:1]])
        for a, b in zip(edges[:-1], edges[1:]):  # tar seal along the saw-cut joints
            tar.append(_ribbon(np.linspace(a, b, 8), 0.07))
    layers = []
    if patches:  # fresh asphalt: darker, smoother
        layers.append((draw.ground_polygon_mask(ctx, patches), min(1.0, p["tar_shade_factor"] + 0.15), 0.6, 0.15))
    for polys, factor, blur, texture in ((tar, p["tar_shade_factor"], 0.5, 0.2), (sheen, p["gloss_factor"], 0.7, 0.5)):
        if polys and factor != 1.0:  # tar bands, then the specular sheen down the middle of the strips
            m = np.zeros((h, w), np.float32)
            for poly in polys:
                draw.ground_polygon_mask(ctx, [poly], step=1.0, mask=m)
            layers.append((np.minimum(m, 1.0), factor, blur, texture))
    return _darken_road(image, ctx, layers, rng) if layers else image.copy()


def render_tire_marks(image: np.ndarray, ctx: IllusionContext, level: dict | int,
                      rng: np.random.Generator) -> np.ndarray:
    """Skid-mark pairs: two parallel dark rubber arcs a track width apart, sweeping across lanes."""
    p = level_params(LEVELS["tire_marks"], level)
    top = LEVELS["tire_marks"][-1]
    h, w = ctx.image_size
    lo, hi = _road_span(ctx)
    mask = np.zeros((h, w), np.uint8)
    light = draw.RoadLight(image, ctx)
    pair_rngs = [np.random.default_rng(s) for s in rng.integers(0, 2**63, top["pair_count"])]
    for i, prng in enumerate(pair_rngs[:p["pair_count"]]):
        direction = float(prng.choice([-1.0, 1.0]))
        length = p["mark_length_m"] * prng.uniform(0.85, 1.15)
        sweep = p["lateral_sweep_m"] * prng.uniform(0.8, 1.2)
        reach = top["lateral_sweep_m"] * 1.2  # placement fits the widest sweep: same start at every level
        d0s = np.clip(prng.uniform(lo + 1.0, hi - 1.0, CANDIDATES), lo + reach * (direction < 0),
                      hi - reach * (direction > 0))
        z_far = introduced(LEVELS["tire_marks"], "pair_count", i, "start_z_far_m", p)
        z0s = Z_NEAR + 1.0 + (z_far - Z_NEAR - 1.0) * prng.random(CANDIDATES)
        k = light.pick(d0s, z0s + 3.0)
        d0, z0 = float(d0s[k]), float(z0s[k])
        t = np.linspace(0.0, 1.0, 48)
        centre = np.stack([d0 + direction * sweep * t ** 2, z0 + length * t], 1)
        tangent = np.gradient(centre, axis=0)
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        normal = np.stack([tangent[:, 1], -tangent[:, 0]], 1)
        strength = 0.35 + 0.65 * np.clip(t * 1.6, 0.0, 1.0)  # braking: faint start, full rubber later
        for side in (-0.5, 0.5):
            track = centre + normal * (side * p["track_width_m"]) + prng.normal(0, 0.01, centre.shape)
            edge_a = track + normal * (p["tire_width_m"] / 2.0)
            edge_b = track - normal * (p["tire_width_m"] / 2.0)
            pa = draw.project(ctx, draw.road_points(ctx, edge_a[:, 0], edge_a[:, 1]))[0]
            pb = draw.project(ctx, draw.road_points(ctx, edge_b[:, 0], edge_b[:, 1]))[0]
            for k in range(len(t) - 1):  # short quads, each with its own rubber density
                quad = np.stack([pa[k], pa[k + 1], pb[k + 1], pb[k]])
                if np.all(np.isfinite(quad)):
                    pts = np.round(quad * (1 << _SHIFT)).astype(np.int32)
                    cv2.fillPoly(mask, [pts], int(255 * strength[k]), _AA, _SHIFT)
    mask = mask.astype(np.float32) * (1.0 / 255.0)
    return _darken_road(image, ctx, [(mask, p["shade_factor"], 0.8, 0.3)], rng)


# ---------------------------------------------------------------------------------------- guard rail
def render_guard_rail(image: np.ndarray, ctx: IllusionContext, level: dict | int,
                      rng: np.random.Generator) -> np.ndarray:
    """A 3D W-beam guard rail on posts along the road edge, nearer to the lane at higher severity."""
    p = level_params(LEVELS["guard_rail"], level)
    out = image.copy()
    rails = rail_offsets(ctx, p, rng)
    grime = rng.uniform(0.9, 1.05, 256)
    light = _rail_light(image, ctx)
    for d_rail, sign in rails:
        _draw_rail(out, ctx, p, d_rail, sign, light, grime)
    return out


def rail_offsets(ctx: IllusionContext, level: dict | int, rng: np.random.Generator) -> list[tuple[float, float]]:
    """(d of the posts, side sign +1 right / -1 left) of each guard rail at `level` (a point, or a severity 1..5);
    draws one number from rng.

    A rail stands offset_from_edge_line_m outside the road's outermost boundary on its side (a marked
    edge line, or an unmarked road edge beyond the camera's lane). With one rail, its side is drawn
    per seed but swapped when only the other side is in view near the camera (same side at every level).
    """
    p = level_params(LEVELS["guard_rail"], level)
    edges = [b.d for b in ctx.road.boundaries] or list(ctx.lane_offsets) or [-1.8, 1.8]
    left, right = min(edges), max(edges)

    def edge_line(side: float) -> float:
        return right if side > 0 else left

    first = draw.visible_side(ctx, 1 if rng.random() < 0.5 else -1, lambda side: edge_line(side) + side * 1.0)
    return [(edge_line(s) + s * p["offset_from_edge_line_m"], float(s)) for s in (first, -first)[:p["sides"]]]


def _rail_light(image: np.ndarray, ctx: IllusionContext) -> np.ndarray:
    """RGB light on an unlit grey object, estimated from the asphalt the scene itself shows.

    The median road colour at a few points between the lanes, relative to daylight asphalt, carries
    the scene's illumination level and tint (noon, sunset, night) over to the steel.
    """
    lanes = np.sort(np.asarray(ctx.lane_offsets, np.float64)) if len(ctx.lane_offsets) >= 2 else np.array([-1.8, 1.8])
    d, z = np.meshgrid((lanes[:-1] + lanes[1:]) / 2.0, np.linspace(6.0, 30.0, 8))
    pix = draw.project(ctx, draw.road_points(ctx, d.ravel(), z.ravel()))[0]
    h, w = ctx.image_size
    ok = np.all(np.isfinite(pix), axis=1)
    u = np.clip(pix[ok, 0].astype(int), 0, w - 1)
    v = np.clip(pix[ok, 1].astype(int), 0, h - 1)
    road_rgb = np.median(image[v, u].astype(np.float64), axis=0) if len(u) else np.full(3, 110.0)
    return np.clip(road_rgb / 110.0, 0.08, 1.2)


def _draw_rail(out: np.ndarray, ctx: IllusionContext, p: dict, d_rail: float, sign: float,
               light: np.ndarray, grime: np.ndarray) -> None:
    """Paint posts and beam segments of one rail into `out` far to near (painter's algorithm)."""
    z_far = RAIL_Z_FAR
    zs = p["z_start_m"] * (z_far / p["z_start_m"]) ** np.linspace(0.0, 1.0, 90)
    d_beam = d_rail - sign * 0.15  # the beam is bolted on the road side of the posts
    yc, half = p["beam_height_m"], p["beam_depth_m"] / 2.0
    # W-beam profile (bottom to top): lit ridge, dark groove, lit ridge, bright top highlight line
    bands = [(yc - half, yc - half * 0.35, 0.85), (yc - half * 0.35, yc + half * 0.35, 0.55),
             (yc + half * 0.35, yc + half * 0.8, 0.95), (yc + half * 0.8, yc + half, 1.35)]
    steel = np.array([168.0, 172.0, 178.0])
    posts = np.arange(np.ceil(p["z_start_m"] / p["post_spacing_m"]) * p["post_spacing_m"], z_far,
                      p["post_spacing_m"])
    items = [(float(z), "post") for z in posts] + [(float(z), "beam") for z in zs[:-1]]
    items.sort(key=lambda it: -it[0])
    seg = {float(z): i for i, z in enumerate(zs[:-1])}
    quads = []  # (d pair, z pair, lift pair, shade, the item's z), in painting order
    for z, kind in items:
        if kind == "post":
            quads.append(((d_rail - 0.08, d_rail + 0.08), (z, z), (0.0, p["post_height_m"]), 0.45, z))
        else:
            i = seg[z]
            quads += [((d_beam, d_beam), (zs[i], zs[i + 1]), (lo_y, hi_y), shade, z) for lo_y, hi_y, shade in bands]
    # every quad's 4 corners (d: a b b a, z: a b b a, lift: a a b b) projected at once, then filled one by one
    d, z, lift = (np.array([[a, b, b, a] if k < 2 else [a, a, b, b] for a, b in (q[k] for q in quads)])
                  for k in range(3))
    pixels, depths = draw.project(ctx, draw.road_points(ctx, d, z, lift=lift))
    for (_, _, _, shade, z), pix, depth in zip(quads, pixels, depths):
        if np.any(depth <= draw.NEAR_Z) or not np.all(np.isfinite(pix)):
            continue
        g = grime[int(z * 7.0) % len(grime)]
        color = np.clip(steel * shade * light * g, 0, 255)
        pts = np.round(pix * (1 << _SHIFT)).astype(np.int32)
        cv2.fillPoly(out, [pts], color.tolist(), _AA, _SHIFT)


RENDERERS: dict[str, Callable] = {
    "road_crack": render_road_crack,
    "road_repair": render_road_repair,
    "tire_marks": render_tire_marks,
    "guard_rail": render_guard_rail,
}
