"""Traffic-obstruction illusions: vehicles, pedestrians and cyclists standing on the lane lines.

Each participant is a small set of 3D primitives (boxes, spheres, wheel rings) anchored at a road
point (d lateral metres, z forward metres) with a heading relative to the road. Primitives are
projected vertex by vertex and filled with OpenCV (painter's order: far objects first, back faces
culled), faces are shaded by the sun direction, and each participant casts a soft ground shadow
(its corners projected along the sun onto the road) plus a dark contact patch. Only the pixels
covered by a participant or its shadow change; the ground-truth lanes stay where they were.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np

from lanevil_train.illusions import draw
from lanevil_train.illusions.context import IllusionContext
from lanevil_train.illusions.parameters import level_params

# Per severity: count of participants, forward-distance range (m) they are placed in, and the
# largest lateral offset (m) of a participant's centre from the lane line it stands on. Level 1's
# single participant stands near enough (8-24 m) to cover at least 0.2 % of a 1280x720 image.
LEVELS: dict[str, list[dict]] = {
    "vehicle": [
        {"count": 1, "z_near_m": 18.0, "z_far_m": 24.0, "line_offset_max_m": 0.8, "truck_prob": 0.0},
        {"count": 1, "z_near_m": 14.0, "z_far_m": 19.0, "line_offset_max_m": 0.8, "truck_prob": 0.2},
        {"count": 2, "z_near_m": 12.0, "z_far_m": 26.0, "line_offset_max_m": 0.8, "truck_prob": 0.3},
        {"count": 3, "z_near_m": 10.0, "z_far_m": 26.0, "line_offset_max_m": 0.8, "truck_prob": 0.3},
        {"count": 4, "z_near_m": 6.5, "z_far_m": 20.0, "line_offset_max_m": 0.8, "truck_prob": 0.35},
    ],
    "pedestrian": [
        {"count": 1, "z_near_m": 7.5, "z_far_m": 10.0, "line_offset_max_m": 0.4},
        {"count": 2, "z_near_m": 7.0, "z_far_m": 12.5, "line_offset_max_m": 0.4},
        {"count": 4, "z_near_m": 7.0, "z_far_m": 16.0, "line_offset_max_m": 0.4},
        {"count": 6, "z_near_m": 7.0, "z_far_m": 16.0, "line_offset_max_m": 0.4},
        {"count": 9, "z_near_m": 5.0, "z_far_m": 13.0, "line_offset_max_m": 0.4},
    ],
    "bicycle": [
        {"count": 1, "z_near_m": 8.0, "z_far_m": 11.0, "line_offset_max_m": 0.4},
        {"count": 2, "z_near_m": 7.0, "z_far_m": 13.0, "line_offset_max_m": 0.4},
        {"count": 3, "z_near_m": 7.0, "z_far_m": 16.0, "line_offset_max_m": 0.4},
        {"count": 4, "z_near_m": 7.0, "z_far_m": 16.0, "line_offset_max_m": 0.4},
        {"count": 6, "z_near_m": 5.0, "z_far_m": 13.0, "line_offset_max_m": 0.4},
    ],
}

# the LEVELS keys that are whole numbers (int parameters of Illusion.parameters(); the others are floats)
INTEGER_KEYS = frozenset({"count"})

_CAR_COLOURS = np.array([[200, 200, 205], [30, 32, 36], [150, 20, 25], [40, 70, 140], [120, 124, 128],
                         [235, 235, 230], [90, 95, 60], [180, 140, 40]], np.float64)
_CLOTH_COLOURS = np.array([[40, 45, 60], [150, 30, 35], [200, 190, 170], [30, 90, 60], [90, 90, 95],
                           [220, 120, 40], [60, 60, 130], [20, 20, 22]], np.float64)
_SKIN = np.array([[224, 180, 150], [160, 110, 80], [100, 70, 50]], np.float64)
_GLASS = (28, 34, 42)
_MAX_SLOTS = 12  # most participants any level places
_TYRE = (22, 22, 24)


@dataclass
class Prim:
    """One primitive in the participant's local frame (x right, y up, z forward, metres).

    kind "box": centre + half sizes; "sphere": centre + radius; "ring": wheel in the y-z plane
    (centre, radius, tube radius). `glow` > 0 marks a lamp (unshaded, lit at night)."""

    kind: str
    centre: tuple[float, float, float]
    size: tuple[float, float, float]
    colour: tuple[float, float, float]
    glow: float = 0.0


@dataclass
class Participant:
    """A traffic participant at road point (d, z), heading (rad, 0 = along the road) and its parts."""

    d: float
    z: float
    heading: float
    prims: list[Prim] = field(default_factory=list)


# ----------------------------------------------------------------------------- builders
def _car(rng: np.random.Generator, truck: bool) -> list[Prim]:
    """Body, greenhouse with dark windows, wheels and tail lights of a car (or a box truck)."""
    col = tuple(_CAR_COLOURS[rng.integers(len(_CAR_COLOURS))])
    if truck:
        w, ln = rng.uniform(2.3, 2.5), rng.uniform(6.5, 8.5)
        cargo_h = rng.uniform(3.0, 3.6)
        box_col = tuple(np.clip(np.array(col) * 0.3 + 170, 0, 255))
        prims = [Prim("box", (0, 0.35 + (cargo_h - 0.35) / 2, -ln * 0.12), (w / 2, (cargo_h - 0.35) / 2, ln * 0.38),
                      box_col),
                 Prim("box", (0, 1.35, ln * 0.38), (w / 2 * 0.97, 1.0, ln * 0.12), col),
                 Prim("box", (0, 2.1, ln * 0.5 - 0.05), (w / 2 * 0.8, 0.3, 0.03), _GLASS)]
        rear_z, light_y = -ln * 0.5, 0.6
        prims.append(Prim("box", (0, 0.72, rear_z - 0.02), (0.015, 0.35 * cargo_h - 0.1, 0.01), (70, 70, 72)))
    else:
        w, ln = rng.uniform(1.7, 1.9), rng.uniform(4.1, 4.8)
        body_top, roof = rng.uniform(0.95, 1.05), rng.uniform(1.40, 1.50)
        prims = [Prim("box", (0, (0.3 + body_top) / 2, 0), (w / 2, (body_top - 0.3) / 2, ln / 2), col),
                 Prim("box", (0, (body_top + roof) / 2, -ln * 0.06), (w / 2 * 0.86, (roof - body_top) / 2,
                                                                       ln * 0.25), _GLASS),
                 Prim("box", (0, roof - 0.02, -ln * 0.06), (w / 2 * 0.84, 0.03, ln * 0.22), col)]
        rear_z, light_y = -ln / 2, body_top - 0.15
    prims.append(Prim("box", (0, 0.4, rear_z - 0.04), (w / 2, 0.08, 0.05), (45, 45, 48)))  # bumper
    r = 0.36 if not truck else 0.5
    for sx in (-1, 1):
        for sz in (-0.32, 0.32):
            prims.insert(0, Prim("box", (sx * (w / 2 - 0.12), r, sz * ln), (0.14, r, r), _TYRE))
        prims.append(Prim("box", (sx * (w / 2 - 0.18), light_y, rear_z - 0.01), (0.15, 0.07, 0.01),
                          (190, 20, 20), glow=1.0))
    return prims


def _pedestrian(rng: np.random.Generator) -> list[Prim]:
    """Legs, torso, arms and head of a walking adult (about 1.6-1.85 m)."""
    h = rng.uniform(1.6, 1.85)
    top, legs = tuple(_CLOTH_COLOURS[rng.integers(8)]), tuple(_CLOTH_COLOURS[rng.integers(8)])
    skin = tuple(_SKIN[rng.integers(3)])
    leg_h, torso_h = 0.47 * h, 0.33 * h
    stride = rng.uniform(0.04, 0.15)
    prims = [Prim("box", (-0.1, leg_h / 2, stride), (0.075, leg_h / 2, 0.08), legs),
             Prim("box", (0.1, leg_h / 2, -stride), (0.075, leg_h / 2, 0.08), legs),
             Prim("box", (0, leg_h + torso_h / 2, 0), (0.2, torso_h / 2, 0.12), top),
             Prim("box", (-0.26, leg_h + torso_h * 0.55, -stride * 0.6), (0.055, torso_h * 0.45, 0.06), top),
             Prim("box", (0.26, leg_h + torso_h * 0.55, stride * 0.6), (0.055, torso_h * 0.45, 0.06), top),
             Prim("sphere", (0, h - 0.11, 0), (0.11, 0.11, 0.11), skin)]
    return prims


def _bicycle(rng: np.random.Generator) -> list[Prim]:
    """Two wheel rings, frame, rider (legs, torso, head) and a red rear lamp."""
    frame = tuple(_CAR_COLOURS[rng.integers(len(_CAR_COLOURS))])
    top = tuple(_CLOTH_COLOURS[rng.integers(8)])
    skin = tuple(_SKIN[rng.integers(3)])
    r = 0.34
    return [Prim("ring", (0, r, -0.52), (r, r, 0.025), _TYRE),
            Prim("ring", (0, r, 0.52), (r, r, 0.025), _TYRE),
            Prim("box", (0, 0.62, 0.0), (0.025, 0.03, 0.5), frame),
            Prim("box", (0, 0.5, -0.2), (0.025, 0.2, 0.025), frame),
            Prim("box", (-0.1, 0.72, -0.1), (0.06, 0.3, 0.07), (40, 40, 50)),
            Prim("box", (0.1, 0.6, 0.05), (0.06, 0.28, 0.07), (40, 40, 50)),
            Prim("box", (0, 1.25, 0.05), (0.18, 0.28, 0.13), top),
            Prim("sphere", (0, 1.66, 0.2), (0.11, 0.11, 0.11), skin),
            Prim("box", (0, 0.75, -0.75), (0.04, 0.03, 0.01), (200, 25, 25), glow=1.0)]


_BUILDERS: dict[str, Callable[[np.random.Generator, dict], list[Prim]]] = {
    "vehicle": lambda rng, lv: _car(rng, bool(rng.random() < lv["truck_prob"])),
    "pedestrian": lambda rng, lv: _pedestrian(rng),
    "bicycle": lambda rng, lv: _bicycle(rng),
}


def layout(name: str, ctx: IllusionContext, level: dict | int, rng: np.random.Generator) -> list[Participant]:
    """Place level['count'] participants on lane lines, one per depth stratum (`level`: a point, or a severity
    1..5 for LEVELS[name][severity-1]).

    The random draws per slot are made the same way at every severity (a fixed number of them, for the most
    participants any level places), so for one rng seed a higher severity keeps the same participants, nearer,
    and adds more.
    """
    lv = level_params(LEVELS[name], level)
    offsets = np.asarray(ctx.lane_offsets if ctx.lane_offsets else (0.0,), np.float64)
    d_cam = float(ctx.road.lateral(0.0, 0.0))
    # lines nearest the camera first (they are in view); shuffle among equally near ones
    order = np.argsort(np.abs(offsets - d_cam) + rng.uniform(0, 0.3, len(offsets)))
    u_z, u_d, u_h = rng.random(_MAX_SLOTS), rng.uniform(-1, 1, _MAX_SLOTS), rng.random(_MAX_SLOTS)
    seeds = rng.integers(0, 2**62, _MAX_SLOTS)
    n = lv["count"]
    edges = np.linspace(lv["z_near_m"], lv["z_far_m"], n + 1)
    out = []
    for i in range(n):
        line = offsets[order[i % min(len(order), 3)]]
        z = float(edges[i] + u_z[i] * (edges[i + 1] - edges[i]))
        d = float(line + u_d[i] * lv["line_offset_max_m"])
        if name == "vehicle":
            heading = 0.12 * (u_h[i] - 0.5)
        elif name == "pedestrian":
            heading = (1.0 if u_h[i] < 0.5 else -1.0) * np.pi / 2 + 0.6 * (u_h[i] % 0.5 - 0.25)
        else:
            heading = (0.0, np.pi / 2, -np.pi / 2)[int(u_h[i] * 3) % 3] + 0.3 * ((u_h[i] * 3) % 1 - 0.5)
        prims = _BUILDERS[name](np.random.default_rng(int(seeds[i])), lv)
        out.append(Participant(d=d, z=z, heading=float(heading), prims=prims))
    return out


# ----------------------------------------------------------------------------- geometry
def _frame(ctx: IllusionContext, p: Participant) -> tuple[np.ndarray, np.ndarray]:
    """World origin (3,) and axes (3x3, columns right/up/forward) of a participant's local frame."""
    origin = draw.road_points(ctx, p.d, p.z)
    ang = np.arctan(float(ctx.road.center_dx(p.z))) + p.heading
    fwd = np.array([np.sin(ang), 0.0, np.cos(ang)])
    up = np.array([0.0, 1.0, 0.0])
    right = np.cross(up, fwd)
    return origin, np.stack([right, up, fwd], axis=1)


def participant_points(ctx: IllusionContext, participant: Participant) -> np.ndarray:
    """World points (N, 3) outlining a participant's parts (box corners, sphere and wheel samples): where it
    stands, for a collision model (closed_loop/collisions.py)."""
    origin, axes = _frame(ctx, participant)
    return np.concatenate([_world_vertices(prim, origin, axes) for prim in participant.prims])


_BOX_FACES = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]])
_BOX_CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)


def _world_vertices(prim: Prim, origin: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """World points outlining a primitive (box corners, sphere/ring samples)."""
    c = np.asarray(prim.centre, np.float64)
    if prim.kind == "box":
        local = c + _BOX_CORNERS * np.asarray(prim.size)
    else:
        t = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        r = prim.size[0]
        local = c + r * np.stack([np.zeros_like(t), np.sin(t), np.cos(t)], 1)
        if prim.kind == "sphere":
            local = np.concatenate([local, c + r * np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], 1)])
    return origin + local @ axes.T


# ----------------------------------------------------------------------------- rendering
def _light(ctx: IllusionContext) -> tuple[np.ndarray, float, float]:
    """Sun direction used for shading/shadows, ambient and direct light strengths."""
    sun = np.asarray(ctx.sun_direction, np.float64)
    if ctx.night or sun[1] <= 0:
        return np.array([0.0, 1.0, 0.0]), 0.16, 0.0
    el = np.arcsin(np.clip(sun[1], -1, 1))
    return sun, 0.55, 0.45 * min(1.0, float(np.sin(el)) * 8.0)


def _shadows(out: np.ndarray, ctx: IllusionContext, parts: list[Participant]) -> np.ndarray:
    """Darken the road under and behind each participant (cast shadow along the sun + contact patch)."""
    h, w = out.shape[:2]
    sun, _, direct = _light(ctx)
    sy = max(float(sun[1]), np.sin(np.radians(8.0)))
    polys_cast, polys_contact = [], []
    for p in parts:
        origin, axes = _frame(ctx, p)
        ground_y = origin[1]
        pts = np.concatenate([_world_vertices(q, origin, axes) for q in p.prims])
        if direct > 0:
            lift = np.maximum(pts[:, 1] - ground_y, 0.0)
            flat = pts - sun[None, :] / sy * lift[:, None]
            flat[:, 1] = ground_y
            pix, depth = draw.project(ctx, flat[draw.in_front(ctx, flat)])
            if len(pix) >= 3 and np.all(np.isfinite(pix)):
                polys_cast.append(cv2.convexHull(pix.astype(np.float32)).reshape(-1, 2))
        foot = pts.copy()
        foot[:, 1] = ground_y
        c = foot.mean(0)
        foot = c + (foot - c) * 1.12
        pix, _ = draw.project(ctx, foot[draw.in_front(ctx, foot)])
        if len(pix) >= 3 and np.all(np.isfinite(pix)):
            polys_contact.append(cv2.convexHull(pix.astype(np.float32)).reshape(-1, 2))
    if not polys_cast and not polys_contact:
        return out
    allpts = np.concatenate(polys_cast + polys_contact)
    sigma = max(1.0, w / 400.0)
    pad = int(np.ceil(3 * 2.5 * sigma)) + 2  # the widest blur (contact patch) fades out inside the ROI
    x0, y0 = np.maximum(np.floor(allpts.min(0)).astype(int) - pad, 0)
    x1, y1 = np.minimum(np.ceil(allpts.max(0)).astype(int) + pad, [w - 1, h - 1])
    if x1 < x0 or y1 < y0:
        return out
    shift = np.array([x0, y0], np.float64)
    roi = (y1 - y0 + 1, x1 - x0 + 1)
    m_cast = draw.fill_polygons(roi, [q - shift for q in polys_cast], value=0.45 * min(1.0, direct * 2.5))
    m_cont = draw.fill_polygons(roi, [q - shift for q in polys_contact], value=0.55)
    m = np.maximum(draw.soften(m_cast, sigma * 1.5), draw.soften(m_cont, sigma * 2.5))
    sub = out[y0:y1 + 1, x0:x1 + 1]
    out[y0:y1 + 1, x0:x1 + 1] = draw.shade(sub, m, 0.0)
    return out


def _draw_participant(out: np.ndarray, ctx: IllusionContext, p: Participant) -> None:
    """Paint one participant's primitives (far first, back faces culled) into `out` in place."""
    sun, ambient, direct = _light(ctx)
    cam = ctx.camera.position
    origin, axes = _frame(ctx, p)
    night = ctx.night
    # at night: street light plus the ego headlights, which light near participants more
    depth0 = float(draw.project(ctx, origin)[1])
    dim = 0.22 + 0.45 * float(np.exp(-max(depth0, 0.0) / 12.0)) if night else 1.0
    items = []
    for q in p.prims:
        v = _world_vertices(q, origin, axes)
        items.append((q.colour != _TYRE, -float(np.linalg.norm(v.mean(0) - cam)), q, v))
    items.sort(key=lambda t: t[:2])  # tyres (under the body) first, then far to near
    for _, _, q, v in items:
        pix, depth = draw.project(ctx, v)
        if np.any(depth <= draw.NEAR_Z) or not np.all(np.isfinite(pix)):
            continue
        base = np.asarray(q.colour, np.float64)
        if q.glow > 0 and night:
            glow = np.clip(base * 1.6 + 60, 0, 255)
            _lamp(out, pix, glow)
            continue
        if q.kind == "box":
            for f in _BOX_FACES:
                quad = v[f]
                n = np.cross(quad[1] - quad[0], quad[3] - quad[0])
                n /= np.linalg.norm(n) + 1e-12
                if np.dot(n, cam - quad.mean(0)) <= 0:
                    continue
                lit = ambient + direct * max(0.0, float(np.dot(n, sun))) + (0.12 if n[1] > 0.5 else 0.0)
                col = np.clip(base * lit * dim, 0, 255)
                _fill(out, pix[f], col)
        elif q.kind == "sphere":
            c, _ = draw.project(ctx, v.mean(0))
            r = float(np.max(np.linalg.norm(pix - c, axis=1)))
            col = np.clip(base * (ambient + direct * 0.6) * dim, 0, 255)
            cv2.circle(out, (int(round(c[0] * 16)), int(round(c[1] * 16))), max(1, int(round(r * 16))),
                       tuple(float(x) for x in col), -1, cv2.LINE_AA, 4)
        else:  # ring: wheel tyre as a closed polyline with perspective thickness
            c, dc = draw.project(ctx, v.mean(0))
            thick = max(1, int(round(ctx.camera.fx * 2 * q.size[2] / max(float(dc), 1e-3))))
            col = np.clip(base * dim, 0, 255)
            cv2.polylines(out, [np.round(pix * 16).astype(np.int32)], True, tuple(float(x) for x in col),
                          thick, cv2.LINE_AA, 4)


def _fill(out: np.ndarray, poly: np.ndarray, col: np.ndarray) -> None:
    """Anti-aliased convex fill of a pixel polygon with an RGB colour."""
    cv2.fillConvexPoly(out, np.round(poly * 16).astype(np.int32), tuple(float(x) for x in col), cv2.LINE_AA, 4)


def _lamp(out: np.ndarray, pix: np.ndarray, col: np.ndarray) -> None:
    """A lit lamp at night: bright core plus a small halo (local blend, stays near the lamp)."""
    c = pix.mean(0)
    r = max(1.0, float(np.max(np.linalg.norm(pix - c, axis=1))))
    h, w = out.shape[:2]
    R = int(np.ceil(r * 3)) + 2
    x0, y0 = max(int(c[0]) - R, 0), max(int(c[1]) - R, 0)
    x1, y1 = min(int(c[0]) + R + 1, w), min(int(c[1]) + R + 1, h)
    if x1 <= x0 or y1 <= y0:
        return
    yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float32)
    dist2 = ((xx - c[0]) ** 2 + (yy - c[1]) ** 2) / (r * r)
    a = np.exp(-dist2 * 0.5) * 0.8
    a[dist2 > 9.0] = 0.0
    sub = out[y0:y1, x0:x1].astype(np.float32)
    sub = sub * (1 - a[..., None]) + col.reshape(1, 1, 3) * a[..., None]
    out[y0:y1, x0:x1] = np.clip(sub + 0.5, 0, 255).astype(np.uint8)
    _fill(out, pix[_BOX_FACES[0]] if len(pix) == 8 else pix, np.clip(col + 40, 0, 255))


def render_participants(image: np.ndarray, ctx: IllusionContext, parts: list[Participant],
                        shadows: bool = True) -> np.ndarray:
    """Draw participants (far to near) and, unless `shadows` is False, their shadows into a copy of `image`."""
    out = np.ascontiguousarray(image.copy())
    cam = ctx.camera.position
    visible = [p for p in parts if draw.in_front(ctx, draw.road_points(ctx, p.d, p.z), draw.NEAR_Z + 2.0)]
    if shadows:
        out = _shadows(out, ctx, visible)
    for p in sorted(visible, key=lambda p: -float(np.linalg.norm(draw.road_points(ctx, p.d, p.z) - cam))):
        _draw_participant(out, ctx, p)
    return out


def footprint_boxes(ctx: IllusionContext, parts: list[Participant]) -> list[tuple[int, int, int, int]]:
    """Pixel boxes (x0, y0, x1, y1) outside which a render of `parts` leaves the image untouched
    (bounds of each participant, its lamps' halos, its contact and cast shadow, plus blur margin)."""
    h, w = ctx.image_size
    sun, _, direct = _light(ctx)
    sy = max(float(sun[1]), np.sin(np.radians(8.0)))
    boxes = []
    for p in parts:
        origin, axes = _frame(ctx, p)
        pts = np.concatenate([_world_vertices(q, origin, axes) for q in p.prims])
        flat = pts.copy()
        if direct > 0:
            flat = pts - sun[None, :] / sy * np.maximum(pts[:, 1] - origin[1], 0)[:, None]
        flat[:, 1] = origin[1]
        c = flat.mean(0)
        allp = np.concatenate([pts, flat, c + (flat - c) * 1.2])
        pix, _ = draw.project(ctx, allp[draw.in_front(ctx, allp)])
        pad = 8 + int(np.ceil(3 * 2.5 * max(1.0, w / 400.0)))
        boxes.append((int(np.floor(pix[:, 0].min())) - pad, int(np.floor(pix[:, 1].min())) - pad,
                      int(np.ceil(pix[:, 0].max())) + pad, int(np.ceil(pix[:, 1].max())) + pad))
    return boxes


def _renderer(name: str) -> Callable[[np.ndarray, IllusionContext, dict | int, np.random.Generator], np.ndarray]:
    def render(image: np.ndarray, ctx: IllusionContext, level: dict | int, rng: np.random.Generator) -> np.ndarray:
        return render_participants(image, ctx, layout(name, ctx, level, rng))
    render.__name__ = f"render_{name}"
    render.__doc__ = f"Draw level['count'] {name}s on the lane lines, with shadows (level: a point or a severity)."
    return render


render_pedestrian = _renderer("pedestrian")
render_vehicle = _renderer("vehicle")
render_bicycle = _renderer("bicycle")

RENDERERS: dict[str, Callable] = {"pedestrian": render_pedestrian, "vehicle": render_vehicle,
                                  "bicycle": render_bicycle}
