"""Shadow illusions: contract (determinism, purity, footprint), darken-only rule, geometry, severity."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import pytest

from lanevil_train.illusions import shadow
from lanevil_train.illusions.context import context_from_scene
from lanevil_train.sim import SceneParams, build_scene, render_scene

NAMES = ("streetlight_shadow", "fence_shadow", "rail_shadow", "wire_shadow")
SCENES = {
    "day": (3, SceneParams()),
    "curve_wet": (5, SceneParams(road="left_curve", weather="wet_noon")),
    "uphill_night": (7, SceneParams(road="uphill", weather="night")),
}


@lru_cache(maxsize=None)
def _scene(key: str, w: int = 320, h: int = 180):
    seed, params = SCENES[key]
    image = render_scene(seed, params, w, h)["image"]
    image.setflags(write=False)
    return image, context_from_scene(build_scene(seed, params, w, h))


def _render(name: str, key: str, severity: int, seed: int, size=(320, 180)) -> tuple[np.ndarray, np.ndarray]:
    image, ctx = _scene(key, *size)
    return image, shadow.RENDERERS[name](image, ctx, severity, np.random.default_rng(seed))


def test_tables_cover_the_four_names_with_monotonic_levels() -> None:
    assert set(shadow.RENDERERS) == set(NAMES) == set(shadow.LEVELS)
    for name in NAMES:
        levels = shadow.LEVELS[name]
        assert len(levels) == 5
        assert all(set(lv) == set(levels[0]) for lv in levels), name
        opac = [lv["opacity"] for lv in levels]
        elev = [lv["sun_elevation_deg"] for lv in levels]
        assert all(a < b for a, b in zip(opac, opac[1:])) and 0 < opac[0] and opac[-1] < 1, name
        assert all(a > b for a, b in zip(elev, elev[1:])), name  # lower sun => longer shadows


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("severity", [1, 2, 3, 4, 5])
def test_runs_deterministic_pure_and_darkens_only(name: str, severity: int) -> None:
    image, ctx = _scene("day")
    before = image.copy()
    out = shadow.RENDERERS[name](image, ctx, severity, np.random.default_rng(11))
    again = shadow.RENDERERS[name](image, ctx, severity, np.random.default_rng(11))
    other = shadow.RENDERERS[name](image, ctx, severity, np.random.default_rng(12))
    assert out.dtype == np.uint8 and out.shape == image.shape
    assert out is not image and np.array_equal(image, before)
    assert np.array_equal(out, again)
    assert not np.array_equal(out, other)
    assert (out != image).any()
    assert (out <= image).all()


@pytest.mark.parametrize("name", NAMES)
def test_darkens_only_on_a_wet_day_road(name: str) -> None:
    for severity in (1, 5):
        image, out = _render(name, "curve_wet", severity, seed=4)
        assert (out <= image).all()
        assert (out < image).sum() > 50


@pytest.mark.parametrize("name", NAMES)
def test_at_night_the_shadow_is_cut_out_of_the_levels_own_light(name: str) -> None:
    # a dark road: the level's low light (a floodlight) lights the ground just around the object's
    # shadow, and the shadow is what stays dark, so it shows even where the scene itself is unlit
    image, ctx = _scene("uphill_night")
    assert ctx.night
    for severity in (1, 5):
        out = shadow.RENDERERS[name](image, ctx, severity, np.random.default_rng(4))
        mask = shadow.shadow_mask(name, ctx, severity, np.random.default_rng(4))
        pool = shadow.light_pool(name, ctx, severity, np.random.default_rng(4))
        gain = out.astype(int).sum(axis=2) - image.astype(int).sum(axis=2)
        assert (gain > 6).sum() > 50
        assert not ((gain > 0) & (pool == 0)).any()  # light only inside the pool
        lit = (pool > 0.3) & (mask < 0.5)  # between slats, bars and wires (blurred at 320x180)
        core = mask >= 0.9 * mask.max()
        assert lit.any() and core.any()
        assert gain[lit].mean() > gain[core].mean() + 10  # the shadow stays dark inside the light


@pytest.mark.parametrize("name", NAMES)
def test_changes_only_inside_the_ground_footprint(name: str) -> None:
    image, ctx = _scene("day")
    for severity in (2, 5):
        out = shadow.RENDERERS[name](image, ctx, severity, np.random.default_rng(21))
        mask = shadow.shadow_mask(name, ctx, severity, np.random.default_rng(21))
        changed = (out != image).any(axis=2)
        assert changed.any()
        assert not (changed & (mask == 0)).any()
        # flat straight road: the footprint lies on the ground, below the horizon row
        cam = ctx.camera
        horizon = cam.cy - cam.fy * math.tan(math.radians(cam.pitch_deg))
        rows = np.nonzero(mask.any(axis=1))[0]
        assert rows.min() > horizon - 1.0


@pytest.mark.parametrize("name", NAMES)
def test_full_size_run(name: str) -> None:
    image, out = _render(name, "day", 4, seed=2, size=(1280, 720))
    assert out.shape == (720, 1280, 3)
    assert (out <= image).all()
    assert (out < image).any(axis=2).mean() > 0.002


@pytest.mark.parametrize("name", NAMES)
def test_darkening_grows_with_severity(name: str) -> None:
    # total darkening (sum over pixels and channels of clean - shadowed) measures area x depth
    per_seed = []
    for key, seed in [("day", 0), ("day", 1), ("day", 2), ("curve_wet", 3), ("curve_wet", 4)]:
        totals = []
        for severity in range(1, 6):
            image, out = _render(name, key, severity, seed)
            totals.append(float((image.astype(np.int64) - out).sum()))
        per_seed.append(totals)
        assert totals[-1] > 2.0 * totals[0], (name, key, seed, totals)
        if name != "streetlight_shadow":
            # lamp shadows move with the sun, so a near lamp-head shadow can leave the frame as
            # it lengthens; the other objects' shadows only grow
            assert all(a < b for a, b in zip(totals, totals[1:])), (name, key, seed, totals)
    mean = np.mean(per_seed, axis=0)
    assert all(a < b for a, b in zip(mean, mean[1:])), (name, mean)


@pytest.mark.parametrize("elevation, azimuth, side", [(30.0, 70.0, 1), (12.0, 135.0, -1), (60.0, 10.0, 1)])
def test_shadow_offset_matches_a_ray_cast_along_the_sun(elevation: float, azimuth: float, side: int) -> None:
    # the sun in the world frame of lanevil_train.sim (azimuth from +z towards +x); a point h metres
    # up must shadow where the ray along -sun meets the flat ground
    az = math.radians(azimuth) * side
    el = math.radians(elevation)
    sun = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    top = np.array([2.0, 5.0, 20.0])
    ground = top - sun * (top[1] / sun[1])
    s = shadow.shadow_offset(elevation, azimuth, side)
    np.testing.assert_allclose([2.0 + 5.0 * s[0], 20.0 + 5.0 * s[1]], [ground[0], ground[2]], atol=1e-9)
    assert np.linalg.norm(s) == pytest.approx(1.0 / math.tan(el))


def test_rail_shadow_lines_run_parallel_to_the_lanes() -> None:
    # straight road: a railing bar's shadow is a band at fixed lateral offset, so the shadow mask
    # sampled along a road line of constant d is (nearly) constant between posts, unlike across d
    _, ctx = _scene("day", 1280, 720)
    mask = shadow.shadow_mask("rail_shadow", ctx, 5, np.random.default_rng(3))
    left, right = ctx.road.left_edge, ctx.road.right_edge
    ds = np.linspace(left + 0.5, right - 0.5, 200)
    zs = np.linspace(8.0, 25.0, 60)
    pix = ctx.camera.project(ctx.road.world_point(ds[:, None], zs[None, :]))
    samples = mask[np.round(pix[..., 1]).astype(int), np.round(pix[..., 0]).astype(int)]  # (d, z)
    across = samples.std(axis=0).mean()        # variation across the road at fixed z: stripes
    along = np.median(samples.std(axis=1))     # variation along the road at fixed d: posts only
    assert across > 0.3
    assert along < 0.5 * across


@pytest.mark.parametrize("factor", [0.35, [0.2, 0.5, 0.9], 1.6])
def test_shade_computes_the_masks_box_only_and_gives_the_same_bytes(factor):
    """draw.shade works on the mask's bounding box; the bytes must be those of the formula over the whole image."""
    from lanevil_train.illusions import draw

    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (40, 60, 3), dtype=np.uint8)
    f = np.asarray(factor, np.float32).reshape(1, 1, -1)

    def everywhere(mask):
        out = image.astype(np.float32) * (1.0 + mask[..., None].astype(np.float32) * (f - 1.0))
        return np.clip(out + 0.5, 0, 255).astype(np.uint8)

    corner = np.zeros((40, 60), np.float32)
    corner[30:, 50:] = rng.random((10, 10))  # touches the image's last row and column
    middle = np.zeros((40, 60), np.float32)
    middle[5:9, 20:41] = 1.0
    middle[12, 3] = 0.5
    for mask in (corner, middle, np.zeros((40, 60), np.float32), rng.random((40, 60)).astype(np.float32)):
        got = draw.shade(image, mask, factor)
        assert got.dtype == np.uint8 and np.array_equal(got, everywhere(mask))
        assert got is not image
    assert draw.nonzero_box(middle) == (slice(5, 13), slice(3, 41))
    assert draw.nonzero_box(np.zeros((4, 4))) is None
    floats = image.astype(np.float32) + 0.4  # a float image is rounded everywhere, as before
    expected = np.clip(floats * (1.0 + middle[..., None] * (f - 1.0)) + 0.5, 0, 255).astype(np.uint8)
    assert np.array_equal(draw.shade(floats, middle, factor), expected)
