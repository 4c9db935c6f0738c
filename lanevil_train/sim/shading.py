"""Per-pixel shading of sky and ground (asphalt, verge, paint, wetness, night lights), vectorised.

All functions work on whole float32 images or row bands; colours are sRGB in 0..1.
"""

from __future__ import annotations

import numpy as np

from lanevil_train.sim import textures
from lanevil_train.sim.paint import paint_alpha
from lanevil_train.sim.presets import BOTTS_RGB, PAINT_RGB
from lanevil_train.sim.scene import Scene

F32 = np.float32


def _rgb(c) -> np.ndarray:
    """A colour as a (3, 1, 1) float32 array (images are channel-first: 3 x h x w)."""
    return np.asarray(c, dtype=F32).reshape(3, 1, 1)


def sky(scene: Scene, a: np.ndarray, m: np.ndarray, rng_offsets: np.ndarray) -> np.ndarray:
    """Sky colour (3, h, w) for rays (a, m): elevation gradient, clouds, sun glow."""
    wx = scene.weather
    norm = 1.0 / np.sqrt(a * a + m * m + 1.0)
    e = np.clip(m * norm, 0.0, 1.0)  # sin(elevation)
    t = e ** F32(0.4)
    zen, hor = _rgb(wx["sky_zenith"]), _rgb(wx["sky_horizon"])
    col = hor + t * (zen - hor)
    cover = wx["clouds"]
    if cover > 0:
        mm = np.maximum(m, F32(0.03))
        cx = a / mm * F32(30.0) + rng_offsets[0]
        cz = F32(60.0) / mm + rng_offsets[1]
        n = textures.sample(textures.noise_texture(256, 2.2, 1), cx, cz)
        dens = np.clip((n * F32(0.5) + F32(cover * 1.2 - 0.6)) * F32(2.0), 0.0, 1.0)
        dens *= np.clip((m - F32(0.01)) * F32(12.0), 0.0, 1.0)  # thin out towards the horizon
        cloud = _rgb(wx["sky_horizon"]) * F32(1.05) if not wx["night"] else _rgb(wx["sky_horizon"]) * F32(1.6)
        shade = F32(0.85) + F32(0.15) * np.clip(n, -1.0, 1.0)
        col += dens * (cloud * shade - col)
    glow = wx["sun_glow"]
    if glow > 0:
        sd = scene.sun_direction.astype(F32)
        cosang = (a * sd[0] + m * sd[1] + sd[2]) * norm
        g = glow * np.exp((cosang - F32(1.0)) * F32(60.0)) + F32(2.0) * np.exp((cosang - F32(1.0)) * F32(4000.0))
        warm = _rgb((1.0, 0.85, 0.55)) if wx["sun"][0] < 15 else _rgb((1.0, 1.0, 0.95))
        col += (g * F32(0.8)) * (warm - col)
    return col


def ground_fields(scene: Scene, a: np.ndarray, m: np.ndarray, z: np.ndarray):
    """Road coordinates and pixel footprints for ground rays: (d, s, fd, fs) as float32 arrays."""
    road = scene.road
    x = a * z
    d = road.lateral(x, z).astype(F32, copy=False)
    s = (road.arc_length(z) + F32(scene.params.travel)).astype(F32, copy=False)
    fd = np.empty_like(d)
    fd[:, 1:] = np.abs(d[:, 1:] - d[:, :-1])
    fd[:, 0] = fd[:, 1] if d.shape[1] > 1 else F32(0.05)
    fs = np.empty_like(s)
    fs[1:] = np.abs(s[1:] - s[:-1])
    fs[0] = fs[1] if s.shape[0] > 1 else F32(0.5)
    # a pixel's footprint is at least its lateral width along the road, too
    fs = np.maximum(fs, fd)
    fd = np.maximum(fd, F32(1e-4))
    return d, s, fd, fs


def ground(scene: Scene, a, m, z, rng_offsets: np.ndarray, sky_refl: np.ndarray,
           light: np.ndarray, paint_gain: np.ndarray | None):
    """Ground colour (3, h, w): asphalt / verge albedo with noise, worn paint, wetness, lighting."""
    p, wx, kind, road = scene.params, scene.weather, scene.kind, scene.road
    d, s, fd, fs = ground_fields(scene, a, m, z)
    # ---- region: asphalt or verge bands beyond the road edge
    out = np.maximum(F32(road.left_edge) - d, d - F32(road.right_edge))  # > 0 outside the asphalt
    colors = [kind["asphalt"]]
    contrast = [0.10]
    edges = [0.0]
    acc = 0.0
    for width, rgb, con in kind["verge"]:
        colors.append(rgb)
        contrast.append(con)
        edges.append(acc)
        acc += width
    region = np.searchsorted(np.asarray(edges[1:], F32), out, side="right").astype(np.intp)
    region = np.where(out > 0, region + 1, 0)
    region = np.minimum(region, len(colors) - 1)
    lut = np.asarray(colors, F32).T.copy()  # (3, regions)
    albedo = np.take(lut, region, axis=1)
    con = np.take(np.asarray(contrast, F32), region)
    # ---- texture: coarse blotches + fine grain faded by footprint (no aliasing far away)
    coarse = textures.sample(textures.noise_texture(256, 2.6, 2), d * F32(3.0) + rng_offsets[2],
                             s * F32(1.5) + rng_offsets[3])
    fine = textures.sample(textures.noise_texture(256, 1.2, 3), d * F32(24.0) + rng_offsets[4],
                           s * F32(24.0) + rng_offsets[5])
    fine_amp = np.clip(F32(1.0) - fs * F32(6.0), 0.0, 1.0)
    inten = F32(1.0) + con * (F32(0.9) * coarse + F32(0.8) * fine * fine_amp)
    # wheel paths: slightly darker, polished bands in each lane
    if road.boundaries:
        w = p.lane_width
        dl = np.mod(d - F32(road.boundaries[0].d), F32(w)) - F32(w / 2.0)
        track = np.exp(-np.square((np.abs(dl) - F32(0.85)) * F32(2.6)))
        inten -= track * F32(0.06) * (region == 0)
    # curb line for urban: a lighter strip right at the edge is part of the verge LUT
    albedo *= inten
    # ---- paint (only on the pixels near a boundary)
    pix, alpha, yellow, dots = paint_alpha(road, d, s, fd, fs, p.dash_length, p.dash_gap,
                                           scene.dash_phase)
    if p.paint_wear > 0 and pix.size:
        wear_n = textures.sample(textures.noise_texture(256, 1.6, 4),
                                 d.reshape(-1)[pix] * F32(20.0) + rng_offsets[7],
                                 s.reshape(-1)[pix] * F32(6.0) + rng_offsets[8])
        keep = np.clip(F32(1.0) - F32(p.paint_wear) * (F32(0.55) + F32(0.6) * wear_n), 0.0, 1.0)
        alpha = alpha * (keep + (F32(1.0) - keep) * dots)  # ceramic dots do not wear
    white, yel = PAINT_RGB["white"], PAINT_RGB["yellow"]
    flat = albedo.reshape(3, -1)
    gain = paint_gain.reshape(-1)[pix] if paint_gain is not None else None
    for c in range(3):
        pc = F32(white[c]) + yellow * F32(yel[c] - white[c])
        pc += dots * (F32(BOTTS_RGB[c]) - pc)
        if gain is not None:
            pc *= gain
        cur = flat[c, pix]
        flat[c, pix] = cur + alpha * (pc - cur)
    # ---- wetness: darker asphalt, sky reflection (Fresnel, stronger at grazing angles), puddles
    col = albedo * light
    wet = wx["wet"]
    if wet > 0:
        norm = 1.0 / np.sqrt(a * a + m * m + 1.0)
        cos_t = np.clip(-m * norm, 0.0, 1.0)
        fres = F32(0.04) + F32(0.96) * (F32(1.0) - cos_t) ** 5
        puddle = np.clip((coarse - F32(0.9)) * F32(3.0), 0.0, 1.0) * (region == 0)
        refl = np.clip(F32(wet) * (fres * F32(0.55) + puddle * F32(0.3)), 0.0, F32(0.7))
        refl.reshape(-1)[pix] *= F32(1.0) - F32(0.6) * alpha
        col *= F32(1.0) - F32(0.45 * wet) * (region <= 1)
        col += refl * (sky_refl * F32(0.85) - col)
    return col, d, s


def fog(col: np.ndarray, depth: np.ndarray, scene: Scene) -> np.ndarray:
    """Blend towards the haze colour with distance (in place); sky pixels (depth inf) are left alone."""
    wx = scene.weather
    f = np.exp(-np.minimum(depth, F32(1e5)) / F32(wx["fog"]))
    f[~np.isfinite(depth)] = 1.0  # the sky has its own haze gradient
    haze = _rgb(wx["haze"])
    col -= haze
    col *= f
    col += haze
    return col
