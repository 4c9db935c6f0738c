"""Roadside dressing: vertical walls parallel to the road (buildings, barriers, tree lines), street
lamps (their light pools and their poles), the ego car's headlights and rain streaks."""

from __future__ import annotations

import math

import cv2
import numpy as np

from lanevil_train.sim import textures
from lanevil_train.sim.scene import Scene

F32 = np.float32
LAMP_HEIGHT = 8.0
LAMP_ARM = 1.6
LAMP_RGB = (1.0, 0.78, 0.50)
FACADES = ((0.80, 0.74, 0.62), (0.62, 0.36, 0.28), (0.60, 0.60, 0.60), (0.85, 0.84, 0.80),
           (0.50, 0.44, 0.38), (0.72, 0.66, 0.55), (0.42, 0.45, 0.50), (0.78, 0.60, 0.45))


def wall_depth_lut(scene: Scene, d_wall: float, a_lo: float, a_hi: float, n_a: int = 256,
                   n_z: int = 200) -> np.ndarray:
    """Forward distance at which a ray with horizontal slope a (x per metre forward) first meets
    the vertical wall at lateral offset d_wall, tabulated on n_a slopes in [a_lo, a_hi]; 1e6 = miss."""
    road = scene.road
    zs = np.geomspace(0.3, 600.0, n_z)
    xw = road.offset_x(d_wall, zs)
    a_tab = np.linspace(a_lo, a_hi, n_a)
    diff = a_tab[:, None] * zs[None, :] - xw[None, :]
    sign0 = -np.sign(road.offset_x(d_wall, 0.0))
    cross = diff * sign0 <= 0
    first = np.argmax(cross, axis=1)
    has = cross.any(axis=1) & (first > 0)
    i1 = np.maximum(first, 1)
    rows = np.arange(n_a)
    d0, d1 = diff[rows, i1 - 1], diff[rows, i1]
    frac = np.clip(d0 / np.where(d0 != d1, d0 - d1, 1.0), 0.0, 1.0)
    z = zs[i1 - 1] + frac * (zs[i1] - zs[i1 - 1])
    return np.where(has, z, 1e6).astype(F32)[None, :]


def wall_hits(scene: Scene, a, m, d_wall: float, a_range: tuple[float, float], zeros: np.ndarray):
    """Per pixel: (z of the wall hit, height of the hit above the road surface there)."""
    lut = wall_depth_lut(scene, d_wall, *a_range)
    n_a = lut.shape[1]
    mapx = ((a - F32(a_range[0])) * F32((n_a - 1) / (a_range[1] - a_range[0]))).astype(F32, copy=False)
    zw = cv2.remap(lut, mapx, zeros, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    y = F32(scene.camera.height_m) + m * zw
    if scene.road.grade != 0.0:
        y = y - scene.road.height(zw).astype(F32)
    return zw, y


def wall_layout(scene: Scene, rng: np.random.Generator) -> list[tuple[str, float, int]]:
    """(kind, lateral offset, side -1 left / +1 right) of every wall, far ones first."""
    kind, road = scene.kind, scene.road
    inner = sum(w for w, _, _ in kind["verge"][:-1])
    walls = []
    for wk in kind["walls"]:
        for side, edge in ((-1, road.left_edge), (1, road.right_edge)):
            if wk == "barrier":
                dist = 0.35
            elif wk == "buildings":
                dist = inner + float(rng.uniform(0.2, kind["wall_gap"]))
            else:  # trees
                dist = inner + kind["wall_gap"] + float(rng.uniform(0.0, 12.0))
            walls.append((wk, edge + side * dist, side))
    order = {"trees": 0, "buildings": 1, "barrier": 2}
    walls.sort(key=lambda w: order[w[0]])
    return walls


def shade_walls(scene: Scene, rng: np.random.Generator, img: np.ndarray, depth: np.ndarray, a, m,
                light: np.ndarray, ground_d: np.ndarray) -> None:
    """Draw every wall into img (3, h, w float) where it is nearer than depth (both updated).

    ground_d is the road offset d of each pixel's ground hit (NaN for sky): only sky pixels and
    ground hits beyond a wall's line can show that wall, which bounds the rows to work on."""
    wx = scene.weather
    a_range = (float(a.min()) - 1e-3, float(a.max()) + 1e-3)
    zeros = np.zeros_like(a)
    open_px = np.isnan(ground_d) | (depth > F32(40.0))  # sky, or far ground
    gd = np.nan_to_num(ground_d)
    flat_img = img.reshape(3, -1)
    flat_depth = depth.reshape(-1)
    sun = scene.sun_direction
    base = np.asarray(FACADES, F32)[rng.integers(len(FACADES), size=64)]
    palette = np.clip(base * rng.uniform(0.85, 1.1, (64, 1)), 0, 1).astype(F32)
    heights = rng.uniform(6.0, 32.0, 64).astype(F32)
    heights[rng.random(64) < 0.12] = 0.0  # gaps between buildings
    seg_len = F32(rng.uniform(10.0, 18.0))
    lit_windows = rng.random(4096) < 0.22
    offs = rng.uniform(0, 256, 4).astype(F32)
    for wk, d_wall, side in wall_layout(scene, rng):
        max_h = {"barrier": 0.85, "buildings": 32.0, "trees": 16.0}[wk]
        # (far ground hits may lie past a curved wall line and back again: keep them too)
        beyond = (gd > F32(d_wall)) if side > 0 else (gd < F32(d_wall))
        beyond |= open_px
        rows = np.flatnonzero(beyond.any(axis=1))
        if rows.size == 0:
            continue
        r = int(rows[-1]) + 1
        zw, y = wall_hits(scene, a[:r], m[:r], d_wall, a_range, zeros[:r])
        cand = beyond[:r] & (zw < depth[:r]) & (y >= 0) & (y < max_h) & (zw < 1e5)
        idx = np.flatnonzero(cand)
        if idx.size == 0:
            continue
        z1, y1 = zw.reshape(-1)[idx], y.reshape(-1)[idx]
        s1 = (scene.road.arc_length(z1) + scene.params.travel).astype(F32)
        face = max(0.0, -side * sun[0]) if sun[1] > 0 else 0.0  # wall faces the road
        if wk == "buildings":
            cell = np.floor(s1 / seg_len).astype(np.int64)
            hb = np.take(heights, cell % 64)
            keep = y1 < hb
            idx, z1, y1, s1, cell, hb = idx[keep], z1[keep], y1[keep], s1[keep], cell[keep], hb[keep]
            col = np.take(palette, cell % 64, axis=0)
            wu = np.mod(s1, F32(3.0)) / F32(3.0)
            wv = np.mod(y1, F32(3.2)) / F32(3.2)
            win = (wu > 0.28) & (wu < 0.72) & (wv > 0.3) & (wv < 0.8) & (y1 > 3.2) & (y1 < hb - 0.8)
            fade = np.clip(F32(1.0) - z1 / F32(140.0), 0.0, 1.0)[:, None]
            if wx["night"]:
                wid = (cell * 131 + np.floor(s1 / F32(3.0)).astype(np.int64) * 17
                       + np.floor(y1 / F32(3.2)).astype(np.int64) * 7) % 4096
                on = np.take(lit_windows, wid) & win
                wcol = np.where(on[:, None], np.asarray((0.95, 0.80, 0.50), F32) * F32(1.0 / 0.04),
                                np.asarray((0.05, 0.05, 0.06), F32))
            else:
                wcol = np.asarray(wx["sky_horizon"], F32) * F32(0.45)
            col = col + (fade * win[:, None]) * (wcol - col)
            gain = (F32(0.6 + 0.5 * face) - F32(0.3 * (0.6 + 0.5 * face)) * (y1 < 3.2)  # shop fronts
                    + F32(0.15 * (0.6 + 0.5 * face)) * (y1 > hb - 0.4))  # cornice
            col = col * gain[:, None]
        elif wk == "barrier":
            n = textures.sample(textures.noise_texture(256, 1.5, 5), s1 * F32(8.0) + offs[0], y1 * F32(8.0))
            gain = (F32(1.0) + F32(0.08) * n - F32(0.25) * (y1 < 0.22) + F32(0.1) * (y1 > 0.7)) \
                * F32(0.7 + 0.4 * face)
            col = np.asarray((0.66, 0.66, 0.63), F32) * gain[:, None]
        else:  # trees: an irregular canopy line
            # crowns: one rounded bump every ~5 m on a slowly varying base height
            base_h = F32(7.0) + F32(1.5) * textures.sample(textures.noise_texture(256, 2.0, 6),
                                                           s1 * F32(0.6) + offs[1], np.full_like(s1, offs[2]))
            q = np.mod(s1 + offs[1], F32(5.0)) * F32(0.4) - F32(1.0)
            top = base_h + F32(2.2) * np.sqrt(np.clip(F32(1.0) - q * q, 0.0, 1.0))
            keep = y1 < top
            idx, z1, y1, s1 = idx[keep], z1[keep], y1[keep], s1[keep]
            n = textures.sample(textures.noise_texture(256, 1.4, 7), s1 * F32(6.0) + offs[3], y1 * F32(6.0))
            col = np.asarray((0.16, 0.25, 0.10), F32) * (F32(0.75) + F32(0.3) * n)[:, None]
            col = col * F32(0.8 + 0.3 * face)
        flat_img[:, idx] = (col * light).T
        flat_depth[idx] = z1


def lamp_sides(scene: Scene) -> list[tuple[float, float, float]]:
    """(lateral offset of the pole, phase along s, spacing) for each row of street lamps."""
    spacing = scene.kind["lamps"]
    if spacing <= 0:
        return []
    rng = np.random.default_rng([scene.seed, 0x1A4B])
    phase = float(rng.uniform(0.0, spacing))
    road = scene.road
    return [(road.left_edge - 0.5, phase, spacing), (road.right_edge + 0.5, phase + spacing / 2.0, spacing)]


def lamp_light(scene: Scene, d: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Intensity (h, w) of the lamp light pools on the ground at road coordinates (d, s)."""
    out = np.zeros_like(d)
    for d_pole, phase, spacing in lamp_sides(scene):
        d_head = d_pole + (LAMP_ARM if d_pole < 0 else -LAMP_ARM)
        ds = np.mod(s - F32(phase) + F32(spacing / 2.0), F32(spacing)) - F32(spacing / 2.0)
        dd = d - F32(d_head)
        out += np.exp((ds * ds + dd * dd) * F32(-1.0 / (2 * 4.5 ** 2)))
    return out


def headlight(a: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Intensity (h, w) of the ego car's low beams on the ground (forward cone, fading with z)."""
    return (np.exp(-np.square(a * F32(3.2))) * np.clip((z - F32(3.0)) * F32(0.3), 0.0, 1.0)
            / (F32(1.0) + np.square(z * F32(1.0 / 22.0))))


def draw_lamps(scene: Scene, img: np.ndarray) -> None:
    """Draw poles, arms and heads of the street lamps (and their glow at night) into the uint8 RGB
    image, far ones first."""
    cam, road, night = scene.camera, scene.road, scene.weather["night"]
    travel = scene.params.travel
    items = []
    for d_pole, phase, spacing in lamp_sides(scene):
        k0 = math.ceil((travel + 2.0 - phase) / spacing)
        k1 = math.floor((travel + 160.0 - phase) / spacing)
        for k in range(k0, k1 + 1):
            z = float(road.z_at_arc_length(np.array([phase + k * spacing - travel]))[0])
            items.append((z, d_pole))
    items.sort(reverse=True)
    pole_col = (0.22, 0.23, 0.24) if not night else (0.05, 0.05, 0.06)
    for z, d_pole in items:
        d_head = d_pole + (LAMP_ARM if d_pole < 0 else -LAMP_ARM)
        base = road.world_point(d_pole, z)
        top = base + np.array([0.0, LAMP_HEIGHT, 0.0])
        head = road.world_point(d_head, z) + np.array([0.0, LAMP_HEIGHT, 0.0])
        pix, dep = cam.project(np.stack([base, top, head]), return_depth=True)
        if (dep <= 0.5).any() or not np.isfinite(pix).all():
            continue
        (u0, v0), (u1, v1), (u2, v2) = pix
        if max(u0, u1, u2) < -50 or min(u0, u1, u2) > cam.width + 50:
            continue
        th = max(1, int(round(0.16 * cam.fx / dep[0])))
        fog = math.exp(-dep[0] / scene.weather["fog"])
        col = tuple(255.0 * float(c * fog + h * (1 - fog)) for c, h in zip(pole_col, scene.weather["haze"]))
        p = lambda u, v: (int(round(u * 4)), int(round(v * 4)))  # noqa: E731  (shift=2 sub-pixel)
        cv2.line(img, p(u0, v0), p(u1, v1), col, th, cv2.LINE_AA, 2)
        cv2.line(img, p(u1, v1), p(u2, v2), col, max(1, th // 2 + 1) if th > 1 else 1, cv2.LINE_AA, 2)
        r = max(1, int(round(0.35 * cam.fx / dep[2])))
        if night:
            _glow(img, u2, v2 + r * 0.5, 1.0 * cam.fx / dep[2])
            cv2.circle(img, p(u2, v2 + r * 0.5), r * 4, (255, 242, 217), -1, cv2.LINE_AA, 2)
        else:
            cv2.ellipse(img, p(u2, v2 + r * 0.3), (r * 4, max(1, r // 2) * 4), 0, 0, 360,
                        (89, 92, 92), -1, cv2.LINE_AA, 2)


def _glow(img: np.ndarray, u: float, v: float, radius: float) -> None:
    """Add a soft warm halo around (u, v) to the uint8 image (night lamps)."""
    h, w = img.shape[:2]
    r = max(2.0, radius)
    x0, x1 = int(max(0, u - 3 * r)), int(min(w, u + 3 * r + 1))
    y0, y1 = int(max(0, v - 3 * r)), int(min(h, v + 3 * r + 1))
    if x0 >= x1 or y0 >= y1:
        return
    xs = (np.arange(x0, x1, dtype=F32) - F32(u))[None, :]
    ys = (np.arange(y0, y1, dtype=F32) - F32(v))[:, None]
    g = np.exp(-(xs * xs + ys * ys) / F32(2 * r * r)) * F32(0.8 * 255.0)
    roi = img[y0:y1, x0:x1].astype(F32) + g[..., None] * np.asarray(LAMP_RGB, F32)
    img[y0:y1, x0:x1] = np.clip(roi, 0, 255).astype(np.uint8)


def rain(img: np.ndarray, rng: np.random.Generator, amount: float) -> None:
    """Slanted bright rain streaks over the uint8 RGB image (in place)."""
    if amount <= 0:
        return
    h, w = img.shape[:2]
    mask = np.zeros((h, w), np.uint8)
    n = int(amount * 0.0012 * h * w) + 1
    x = rng.uniform(0, w, n)
    y = rng.uniform(0, h, n)
    length = rng.uniform(0.03, 0.09, n) * h
    slant = rng.normal(0.15, 0.03)
    for xi, yi, li in zip(x, y, length):
        cv2.line(mask, (int(xi), int(yi)), (int(xi + slant * li), int(yi + li)), 255, 1, cv2.LINE_AA)
    alpha = (mask.astype(F32) * F32(0.22 / 255.0))[..., None]
    blend = img.astype(F32)
    blend += alpha * (np.asarray((217.0, 222.0, 230.0), F32) - blend)
    img[...] = np.rint(blend).astype(np.uint8)
