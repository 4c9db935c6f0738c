"""Reflection illusions: contract (determinism, no input mutation), brighten-only, footprint on the
road, effect growing with severity, and the shape of each reflection."""

from __future__ import annotations

import functools

import cv2
import numpy as np
import pytest

from lanevil_train.illusions import draw
from lanevil_train.illusions import reflection as R
from lanevil_train.illusions.context import context_from_scene
from lanevil_train.sim import SceneParams, build_scene, render_scene

NAMES = ("sunlight_reflection", "streetlight_reflection", "vehicle_reflection")
W, H = 320, 180


@functools.lru_cache(maxsize=None)
def _case(weather: str, seed: int = 0, w: int = W, h: int = H):
    params = SceneParams(weather=weather)
    ctx = context_from_scene(build_scene(seed, params, w, h))
    img = render_scene(seed, params, w, h)["image"]
    img.setflags(write=False)
    return img, ctx


def _run(name: str, severity: int, seed: int = 0, weather: str = "night", scene_seed: int = 0,
         size: tuple[int, int] = (W, H)) -> tuple[np.ndarray, np.ndarray]:
    img, ctx = _case(weather, scene_seed, *size)
    out = R.RENDERERS[name](img, ctx, severity, np.random.default_rng(seed))
    return img, out


def test_tables_cover_all_names_with_five_levels_of_plain_numbers():
    assert set(R.RENDERERS) == set(R.LEVELS) == set(NAMES)
    for name in NAMES:
        levels = R.LEVELS[name]
        assert len(levels) == 5
        assert all(set(lv) == set(levels[0]) for lv in levels)
        assert all(isinstance(v, (int, float)) for lv in levels for v in lv.values())
        assert levels[4]["intensity"] > levels[0]["intensity"]


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("severity", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("weather", ["night", "wet_noon"])
def test_contract_brightens_only_deterministic_and_input_untouched(name, severity, weather):
    img, ctx = _case(weather)
    before = img.copy()
    a = R.RENDERERS[name](img, ctx, severity, np.random.default_rng(7))
    b = R.RENDERERS[name](img, ctx, severity, np.random.default_rng(7))
    c = R.RENDERERS[name](img, ctx, severity, np.random.default_rng(8))
    assert a.dtype == np.uint8 and a.shape == img.shape and a is not img
    assert np.array_equal(img, before)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert np.all(a >= img), "a reflection must never darken a pixel"
    assert np.any(a > img)


@pytest.mark.parametrize("name", NAMES)
def test_full_size_runs_and_changes_a_moderate_part_of_the_image(name):
    img, out = _run(name, 3, size=(1280, 720))
    changed = np.any(out != img, axis=2).mean()
    assert 0.002 < changed < 0.5
    assert np.all(out >= img)


@pytest.mark.parametrize("name", NAMES)
def test_streaks_stay_on_the_asphalt(name, monkeypatch):
    # with the light-source glows switched off, every changed pixel must lie on the road surface
    monkeypatch.setattr(R, "_glow", lambda *a, **k: None)
    for weather in ("night", "wet_noon"):
        img, ctx = _case(weather)
        # the asphalt as draw.road_mask sees it, grown by one pixel for anti-aliasing differences
        road = cv2.dilate((draw.road_mask(ctx, far=200.0) > 0).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        for severity in (1, 5):
            out = R.RENDERERS[name](img, ctx, severity, np.random.default_rng(3))
            changed = np.any(out != img, axis=2)
            assert changed.any()
            assert not np.any(changed & ~road)


def _effect(img: np.ndarray, out: np.ndarray) -> tuple[float, int]:
    """Total added brightness and changed-pixel count."""
    return float((out.astype(np.int64) - img).sum()), int(np.any(out != img, axis=2).sum())


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_effect_grows_with_severity(name, seed):
    for weather in ("night", "wet_noon", "sunset"):
        effects = [_effect(*_run(name, s, seed=seed, weather=weather, scene_seed=seed)) for s in range(1, 6)]
        added = [e[0] for e in effects]
        area = [e[1] for e in effects]
        assert all(b > a for a, b in zip(added, added[1:])), (weather, added)
        assert all(b >= a for a, b in zip(area, area[1:])), (weather, area)
        assert added[4] > 3 * added[0]


def test_sun_glare_washes_out_the_road_at_level_five():
    img, ctx = _case("wet_noon")
    out = R.render_sunlight_reflection(img, ctx, 5, np.random.default_rng(0))
    gain = out.astype(np.int64).sum(axis=2) - img.astype(np.int64).sum(axis=2)
    hot = gain > 0
    # a sizeable patch, part of it saturated almost to white
    assert hot.sum() > 0.02 * W * H
    assert np.sum(out.min(axis=2)[hot] >= 235) > 50
    # the glitter path runs towards the sun: taller than wide in the image
    ys, xs = np.nonzero(gain > 60)
    assert (ys.max() - ys.min()) > 0.8 * (xs.max() - xs.min())


def _tallest_streak_aspect(img: np.ndarray, out: np.ndarray) -> float:
    mask = ((out.astype(np.int64) - img).sum(axis=2) > 40).astype(np.uint8)
    n, _, stats, _ = cv2.connectedComponentsWithStats(mask)
    best = max(range(1, n), key=lambda i: stats[i, cv2.CC_STAT_AREA])
    return stats[best, cv2.CC_STAT_HEIGHT] / stats[best, cv2.CC_STAT_WIDTH]


def test_street_lamp_streaks_are_long_and_narrow_like_lane_lines():
    img, out = _run("streetlight_reflection", 5, weather="night", size=(640, 360))
    assert _tallest_streak_aspect(img, out) > 2.0


def test_street_lamp_colour_is_white_or_sodium_yellow():
    img, ctx = _case("night")
    seen = set()
    for seed in range(8):
        out = R.render_streetlight_reflection(img, ctx, 5, np.random.default_rng(seed))
        gain = out.astype(np.float64) - img
        on = gain.sum(axis=2) > 60
        # the screen-blend layer, per channel: gain / headroom
        r, g, b = ((gain[..., c] / np.maximum(255.0 - img[..., c], 1.0))[on].mean() for c in range(3))
        seen.add("yellow" if b < 0.6 * r else "white")
        assert r >= g >= b
    assert seen == {"white", "yellow"}


def test_vehicle_reflections_include_red_tail_light_streaks():
    img, ctx = _case("night")
    reds = 0
    for seed in range(4):
        out = R.render_vehicle_reflection(img, ctx, 5, np.random.default_rng(seed))
        gain = out.astype(np.int64) - img
        reds += int(np.sum((gain[..., 0] > 60) & (gain[..., 1] < 0.3 * gain[..., 0])))
    assert reds > 40


def test_streetlight_streaks_are_stronger_at_night_than_by_day():
    img_n, ctx_n = _case("night")
    img_d, ctx_d = _case("wet_noon")
    # same geometry for both (same seed), so compare the added light per changed pixel
    out_n = R.render_streetlight_reflection(img_n, ctx_n, 4, np.random.default_rng(0))
    out_d = R.render_streetlight_reflection(img_d, ctx_d, 4, np.random.default_rng(0))
    layer = [((o.astype(np.float64) - i) / np.maximum(255.0 - i, 1)).max(axis=2).max() for o, i in
             ((out_n, img_n), (out_d, img_d))]
    assert layer[0] > layer[1] * 1.2


def test_sun_glare_follows_a_low_scene_sun():
    # sunset: the scene's sun is low, 20 degrees left; the glare path must lie left of the image centre
    img, ctx = _case("sunset")
    assert 0 < ctx.sun_direction[1] < 0.2 and ctx.sun_direction[0] < 0
    for seed in range(4):
        out = R.render_sunlight_reflection(img, ctx, 3, np.random.default_rng(seed))
        ys, xs = np.nonzero((out.astype(np.int64) - img).sum(axis=2) > 60)
        assert xs.mean() < ctx.camera.cx - 10


@pytest.mark.parametrize("yaw", [-20.0, 20.0])
def test_yawed_camera_still_gets_reflections_on_its_road(yaw):
    # a strongly yawed camera puts the near road corners behind the image plane; the road (and the
    # reflections on it) must still be found further ahead
    from lanevil_train.illusions.recover import fallback_context

    ctx = fallback_context((H, W), yaw_deg=yaw, num_lanes=3, night=True)
    img = np.full((H, W, 3), 40, np.uint8)
    road = draw.road_mask(ctx, far=200.0) > 0  # the shared road mask copes with the yaw
    assert road.mean() > 0.05
    for name in NAMES:
        out = R.RENDERERS[name](img, ctx, 4, np.random.default_rng(0))
        changed = np.any(out != img, axis=2)
        assert changed[road].sum() > 100
        assert np.all(out >= img)


def test_wrong_image_is_rejected():
    img, ctx = _case("night")
    with pytest.raises(ValueError, match="uint8"):
        R.render_sunlight_reflection(img.astype(np.float32), ctx, 1, np.random.default_rng(0))
    with pytest.raises(ValueError, match="does not match"):
        R.render_sunlight_reflection(img[:100], ctx, 1, np.random.default_rng(0))
