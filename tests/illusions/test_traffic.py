"""Traffic-obstruction illusions: contract, determinism, locality, occlusion of lanes, light."""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import numpy as np
import pytest

from lanevil_train.illusions.context import context_from_scene
from lanevil_train.illusions.traffic import LEVELS, RENDERERS, footprint_boxes, layout, render_participants
from lanevil_train.sim import SceneParams, build_scene, render_scene

NAMES = ("pedestrian", "vehicle", "bicycle")
W, H = 320, 180


@lru_cache(maxsize=None)
def _case(seed: int, weather: str = "clear_noon", w: int = W, h: int = H):
    params = SceneParams(weather=weather)
    sample = render_scene(seed, params, w, h)
    img = sample["image"]
    img.setflags(write=False)
    return img, sample["lanes"], context_from_scene(build_scene(seed, params, w, h))


def test_registry_and_levels_shape():
    assert set(RENDERERS) == set(NAMES) == set(LEVELS)
    for name in NAMES:
        lv = LEVELS[name]
        assert len(lv) == 5
        counts = [x["count"] for x in lv]
        near = [x["z_near_m"] for x in lv]
        far = [x["z_far_m"] for x in lv]
        assert counts[0] == 1 and counts == sorted(counts) and counts[-1] > counts[0]
        assert near == sorted(near, reverse=True) and near[-1] < near[0]  # closer with severity
        assert all(a < b for a, b in zip(near, far))


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("severity", [1, 2, 3, 4, 5])
def test_runs_deterministic_and_pure(name, severity):
    img, _, ctx = _case(0)
    before = img.copy()
    a = RENDERERS[name](img, ctx, severity, np.random.default_rng(7))
    b = RENDERERS[name](img, ctx, severity, np.random.default_rng(7))
    c = RENDERERS[name](img, ctx, severity, np.random.default_rng(8))
    assert a.dtype == np.uint8 and a.shape == img.shape and a is not img
    assert np.array_equal(img, before)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert np.any(a != img)


@pytest.mark.parametrize("name", NAMES)
def test_full_resolution(name):
    img, _, ctx = _case(1, "clear_noon", 1280, 720)
    out = RENDERERS[name](img, ctx, 3, np.random.default_rng(1))
    assert out.shape == (720, 1280, 3) and out.dtype == np.uint8
    changed = np.any(out != img, axis=2).mean()
    assert 0.001 < changed < 0.5


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("severity,weather", [(1, "sunset"), (3, "sunset"), (1, "night"), (5, "clear_noon")])
def test_pixels_outside_footprint_unchanged(name, severity, weather):
    img, _, ctx = _case(2, weather)  # sunset: low sun, the longest shadows; night: lamp halos
    out = RENDERERS[name](img, ctx, severity, np.random.default_rng(3))
    parts = layout(name, ctx, severity, np.random.default_rng(3))
    inside = np.zeros(img.shape[:2], bool)
    for x0, y0, x1, y1 in footprint_boxes(ctx, parts):
        inside[max(y0, 0):max(y1 + 1, 0), max(x0, 0):max(x1 + 1, 0)] = True
    changed = np.any(out != img, axis=2)
    assert changed.any()
    assert not np.any(changed & ~inside)
    assert inside.mean() < 0.9  # the footprint is a real restriction


def _covered_fraction(name, severity, seed, weather="clear_noon", shadows=True):
    """Fraction of GT lane points whose pixel differs (full render, or the occluders alone)."""
    img, lanes, ctx = _case(seed, weather)
    if shadows:
        out = RENDERERS[name](img, ctx, severity, np.random.default_rng(seed))
    else:
        out = render_participants(img, ctx, layout(name, ctx, severity, np.random.default_rng(seed)),
                                  shadows=False)
    pts = np.concatenate([np.round(lane).astype(int) for lane in lanes])
    changed = np.any(out != img, axis=2)
    return float(changed[pts[:, 1], pts[:, 0]].mean())


@pytest.mark.parametrize("name", NAMES)
def test_occluders_cover_lane_points_more_with_severity(name):
    # the participants themselves (no shadows): strictly more lane points hidden at each level
    for seed, weather in ((0, "clear_noon"), (1, "sunset"), (4, "wet_noon")):
        fr = [_covered_fraction(name, s, seed, weather, shadows=False) for s in range(1, 6)]
        assert fr[0] > 0.0, (seed, fr)
        assert all(b > a for a, b in zip(fr, fr[1:])), (seed, fr)
        assert fr[4] > 3 * fr[0] and fr[4] > 0.1, (seed, fr)


@pytest.mark.parametrize("name", NAMES)
def test_full_render_changes_more_lane_points_with_severity(name):
    # with shadows (long at sunset) the growth is checked over two-level steps
    for seed, weather in ((0, "clear_noon"), (1, "sunset"), (4, "wet_noon")):
        fr = [_covered_fraction(name, s, seed, weather) for s in range(1, 6)]
        full = [_covered_fraction(name, s, seed, weather, shadows=False) for s in range(1, 6)]
        assert all(f >= g for f, g in zip(fr, full)), (seed, fr, full)  # shadows only add changes
        assert fr[0] > 0.0 and fr[0] < fr[2] < fr[4], (seed, fr)


def test_ground_truth_lanes_untouched_by_rendering():
    img, lanes, ctx = _case(0)
    copies = [lane.copy() for lane in lanes]
    RENDERERS["vehicle"](img, ctx, 5, np.random.default_rng(0))
    assert all(np.array_equal(a, b) for a, b in zip(lanes, copies))


def test_shadow_falls_away_from_the_sun():
    img, _, ctx = _case(0)
    low = np.sin(np.radians(20.0))
    mean_x = []
    for side in (1.0, -1.0):  # sun to the right, then to the left
        sun = np.array([side * np.cos(np.radians(20.0)), low, 0.0])
        c = replace(ctx, sun_direction=sun)
        out = RENDERERS["vehicle"](img, c, 3, np.random.default_rng(5))
        dark = np.all(out.astype(int) < img.astype(int), axis=2)
        mean_x.append(np.nonzero(dark)[1].mean())
    assert mean_x[0] < mean_x[1] - 2.0  # sun right -> shadows lean left


def test_night_tail_lights_are_lit():
    img, _, ctx = _case(0, "night")
    assert ctx.night
    out = RENDERERS["vehicle"](img, ctx, 4, np.random.default_rng(2)).astype(int)
    changed = np.any(out != img, axis=2)
    red = changed & (out[..., 0] > 150) & (out[..., 0] > out[..., 1] + 60)
    assert red.sum() >= 4
    # the bodies themselves stay dim: most changed pixels are darker than 90
    assert np.median(out[changed].max(axis=1)) < 90


def test_daylight_faces_are_shaded_by_the_sun():
    img, _, ctx = _case(0)
    bright = replace(ctx, sun_direction=np.array([0.0, 1.0, 0.0]))
    night_like = replace(ctx, night=True)
    a = RENDERERS["pedestrian"](img, bright, 4, np.random.default_rng(1)).astype(int)
    b = RENDERERS["pedestrian"](img, night_like, 4, np.random.default_rng(1)).astype(int)
    body = np.any(a != img, axis=2) & np.any(b != img, axis=2)
    assert a[body].mean() > b[body].mean() + 20
