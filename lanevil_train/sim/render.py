"""render_scene: (seed, params, size) -> {"image", "lanes", "meta"}, a pure function of its inputs."""

from __future__ import annotations

import cv2
import numpy as np

from lanevil_train.sim import dressing, shading
from lanevil_train.sim.params import SceneParams, sample_scene_params
from lanevil_train.sim.scene import GT_MAX_DISTANCE, Scene, build_scene

F32 = np.float32


def shade_scene(scene: Scene) -> np.ndarray:
    """Render the image (uint8 h x w x 3 RGB) of a Scene."""
    cam, wx = scene.camera, scene.weather
    rng = np.random.default_rng([scene.seed, 0x7E47])
    offsets = rng.uniform(0.0, 256.0, 12).astype(F32)
    a, m, dz = cam.pixel_grid_rays(F32)
    z = scene.road.intersect(a, m, cam.height_m)
    z = np.where(dz > 0, z, F32(np.inf))
    hit = np.isfinite(z)
    h, w = a.shape
    img = np.empty((3, h, w), F32)
    depth = np.where(hit, z, F32(np.inf)).astype(F32)
    ground_d = np.full((h, w), np.nan, F32)

    # sky everywhere a ray misses the ground (row band above the lowest miss)
    miss_rows = np.flatnonzero(~hit.all(axis=1))
    hit_rows = np.flatnonzero(hit.any(axis=1))
    r_sky = int(miss_rows[-1]) + 1 if miss_rows.size else 0
    r_gnd = int(hit_rows[0]) if hit_rows.size else h
    if r_sky > 0:
        img[:, :r_sky] = shading.sky(scene, a[:r_sky], m[:r_sky], offsets)

    if r_gnd < h:
        ga, gm = a[r_gnd:], m[r_gnd:]
        gz = np.where(hit[r_gnd:], z[r_gnd:], F32(1e5))
        sky_refl = None
        if wx["wet"] > 0:
            sky_refl = shading.sky(scene, ga, -gm, offsets)
        light = np.asarray(wx["light"], F32).reshape(3, 1, 1)
        paint_gain = None
        if wx["night"]:
            d_tmp, s_tmp, _, _ = shading.ground_fields(scene, ga, gm, gz)
            lamps = dressing.lamp_light(scene, d_tmp, s_tmp)
            head = dressing.headlight(ga, gz)
            light = (light + lamps * (np.asarray(dressing.LAMP_RGB, F32) * F32(1.3)).reshape(3, 1, 1)
                     + head * (np.asarray((1.0, 0.97, 0.9), F32) * F32(1.3)).reshape(3, 1, 1))
            paint_gain = F32(1.0) + F32(1.2) * head
        col, gd, _ = shading.ground(scene, ga, gm, gz, offsets, sky_refl, light, paint_gain)
        band_hit = hit[r_gnd:]
        ground_d[r_gnd:] = np.where(band_hit, gd, F32(np.nan))
        if r_gnd < r_sky:  # rows with both: keep the sky where the ray misses
            np.copyto(img[:, r_gnd:], col, where=band_hit[None])
        else:
            img[:, r_gnd:] = col
    light_w = np.asarray(wx["light"], F32)
    dressing.shade_walls(scene, rng, img, depth, a, m, light_w, ground_d)
    shading.fog(img, depth, scene)
    np.clip(img, 0.0, 1.0, out=img)
    img *= F32(255.0)
    out = cv2.merge([img[0].astype(np.uint8), img[1].astype(np.uint8), img[2].astype(np.uint8)])
    dressing.draw_lamps(scene, out)
    dressing.rain(out, rng, wx["rain"])
    if wx["rain"] > 0:
        out = cv2.GaussianBlur(out, (3, 3), 0.8)
    return out


def render_scene(seed: int, params: SceneParams | None = None, width: int = 1280,
                 height: int = 720) -> dict:
    """Render one road scene: {"image": uint8 HxWx3 RGB, "lanes": [(N, 2) pixel polylines, left to
    right, y descending], "meta": {...}}. params=None samples params from the seed."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed: expected an integer, got {seed!r}")
    if params is None:
        params = sample_scene_params(int(seed))
    scene = build_scene(int(seed), params, width, height)
    image = shade_scene(scene)
    lanes, names, offsets = scene.lanes()
    meta = {
        "seed": int(seed),
        "road": params.road,
        "weather": params.weather,
        "scene_kind": params.scene_kind,
        "num_lanes": params.num_lanes,
        "markings": names,
        "lane_offsets_m": offsets,
        "width": int(width),
        "height": int(height),
        "camera": scene.camera.as_dict(),
        "road_geometry": scene.road.as_dict(),
        "sun_direction": scene.sun_direction.tolist(),
        "gt_max_distance_m": GT_MAX_DISTANCE,
        "dash_phase_m": scene.dash_phase,
        "params": params.as_dict(),
    }
    return {"image": image, "lanes": lanes, "meta": meta}
