"""Tests for the road-damage illusions (road_crack, road_repair, tire_marks, guard_rail)."""

from __future__ import annotations

import numpy as np
import pytest

from lanevil_train.illusions import draw
from lanevil_train.illusions.context import context_from_scene
from lanevil_train.illusions.road_damage import LEVELS, RAIL_Z_FAR, RENDERERS, rail_offsets
from lanevil_train.sim import SceneParams, build_scene, render_scene

NAMES = ("road_crack", "road_repair", "tire_marks", "guard_rail")
SURFACE = ("road_crack", "road_repair", "tire_marks")
W, H = 320, 180

_CACHE: dict = {}


def _case(seed: int = 3, weather: str = "clear_noon", road: str = "straight", w: int = W, h: int = H):
    """(clean image, context) of a simulated scene, cached."""
    key = (seed, weather, road, w, h)
    if key not in _CACHE:
        params = SceneParams(weather=weather, road=road)
        img = render_scene(seed, params, w, h)["image"]
        _CACHE[key] = (img, context_from_scene(build_scene(seed, params, w, h)))
    return _CACHE[key]


def _render(name: str, severity: int, seed: int = 0, **scene):
    img, ctx = _case(**scene)
    return img, ctx, RENDERERS[name](img, ctx, severity, np.random.default_rng(seed))


def _changed(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.any(a != b, axis=-1)


def test_tables_complete_and_numeric():
    assert set(RENDERERS) == set(NAMES) == set(LEVELS)
    for name in NAMES:
        assert len(LEVELS[name]) == 5
        keys = set(LEVELS[name][0])
        for params in LEVELS[name]:
            assert set(params) == keys
            assert all(isinstance(v, (int, float)) for v in params.values())


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("severity", [1, 2, 3, 4, 5])
def test_runs_deterministic_and_pure(name, severity):
    img, ctx = _case()
    before = img.copy()
    a = RENDERERS[name](img, ctx, severity, np.random.default_rng(7))
    b = RENDERERS[name](img, ctx, severity, np.random.default_rng(7))
    c = RENDERERS[name](img, ctx, severity, np.random.default_rng(8))
    assert a.dtype == np.uint8 and a.shape == img.shape
    assert a is not img
    np.testing.assert_array_equal(img, before)  # input untouched
    np.testing.assert_array_equal(a, b)  # same seed => same bytes
    assert _changed(a, img).any(), f"{name} s{severity} changed nothing"
    assert not np.array_equal(a, c), f"{name} s{severity}: seeds 7 and 8 gave identical images"


@pytest.mark.parametrize("name", NAMES)
def test_full_hd_runs(name):
    img, ctx, out = _render(name, 5, w=1280, h=720)
    assert out.shape == (720, 1280, 3)
    frac = _changed(out, img).mean()
    assert 0.001 < frac < 0.3


@pytest.mark.parametrize("name", SURFACE)
@pytest.mark.parametrize("weather", ["clear_noon", "wet_noon", "night"])
def test_surface_damage_only_on_road_and_only_darkens(name, weather):
    for severity in (1, 3, 5):
        img, ctx, out = _render(name, severity, seed=severity, weather=weather, road="left_curve")
        changed = _changed(out, img)
        assert changed.sum() > 0
        road = draw.road_mask(ctx) > 0
        assert not (changed & ~road).any(), f"{name} s{severity} changed {int((changed & ~road).sum())} off-road px"
        if name != "road_repair":  # repair strips carry a glossy sheen; cracks and rubber only darken
            assert np.all(out.astype(int) <= img.astype(int))


def _darkening(img: np.ndarray, out: np.ndarray) -> float:
    return float(np.clip(img.astype(np.float64) - out, 0, None).sum())


@pytest.mark.parametrize("name", SURFACE)
def test_surface_effect_grows_with_severity(name):
    for seed in (0, 1, 2):
        area, dark = [], []
        for severity in range(1, 6):
            img, _, out = _render(name, severity, seed=seed)
            area.append(int(_changed(out, img).sum()))
            dark.append(_darkening(img, out))
        assert all(a < b for a, b in zip(area, area[1:])), f"{name} seed {seed}: changed area {area}"
        assert all(a < b for a, b in zip(dark, dark[1:])), f"{name} seed {seed}: darkening {dark}"


def test_crack_level5_is_a_network_level1_is_hairline():
    img, _, s1 = _render("road_crack", 1, w=640, h=360)
    _, _, s5 = _render("road_crack", 5, w=640, h=360)
    c1, c5 = _changed(s1, img).sum(), _changed(s5, img).sum()
    assert c5 > 4 * c1  # level 1 is visible (issue 10), level 5 is a network several times larger
    # hairlines are faint: the mean darkening of changed pixels is much lower than at level 5
    d1 = _darkening(img, s1) / max(c1, 1)
    d5 = _darkening(img, s5) / max(c5, 1)
    assert d1 < 0.6 * d5


def test_repair_has_lane_like_strip_parallel_to_lanes():
    img, ctx, out = _render("road_repair", 5, seed=4, w=640, h=360)
    changed = _changed(out, img)
    rows = np.nonzero(changed.any(axis=1))[0]
    # a strip tens of metres long parallel to the lanes spans many image rows towards the horizon
    assert rows.max() - rows.min() > 0.15 * 360
    _, _, out1 = _render("road_repair", 1, seed=4, w=640, h=360)
    assert _changed(out1, img).sum() < changed.sum()


def test_tire_marks_are_pairs_a_track_width_apart():
    img, ctx = _case(w=640, h=360)
    out = RENDERERS["tire_marks"](img, ctx, 1, np.random.default_rng(5))  # one pair
    changed = _changed(out, img)
    # on some image row the marks show as two separate runs of changed pixels
    runs = [np.count_nonzero(np.diff(changed[v].astype(np.int8)) == 1) for v in range(360)]
    assert max(runs) >= 2


def _rail_hull(ctx, severity: int, seed: int) -> np.ndarray:
    """Mask of the boxes (d +- 0.35 m, up to 1.2 m high) that hold each guard rail."""
    p = LEVELS["guard_rail"][severity - 1]
    rails = rail_offsets(ctx, severity, np.random.default_rng(seed))
    h, w = ctx.image_size
    mask = np.zeros((h, w), np.float32)
    zs = np.geomspace(p["z_start_m"] - 0.2, RAIL_Z_FAR + 1.0, 200)
    for d_rail, _ in rails:
        for za, zb in zip(zs[:-1], zs[1:]):
            for da, db in ((d_rail - 0.35, d_rail + 0.35), (d_rail - 0.35, d_rail - 0.35),
                           (d_rail + 0.35, d_rail + 0.35)):
                for ya, yb in ((0.0, 0.0), (1.2, 1.2), (0.0, 1.2)):
                    corners = draw.road_points(ctx, np.array([da, db, db, da]), np.array([za, za, zb, zb]),
                                               lift=np.array([ya, ya, yb, yb]) if ya == yb
                                               else np.array([ya, yb, yb, ya]))
                    pix = draw.project(ctx, corners)[0]
                    draw.fill_polygons((h, w), [pix], mask=mask)
    return mask > 0


@pytest.mark.parametrize("severity", [1, 3, 5])
def test_guard_rail_stays_in_its_3d_box_and_occludes(severity):
    img, ctx = _case(seed=11, w=640, h=360)
    out = RENDERERS["guard_rail"](img, ctx, severity, np.random.default_rng(2))
    changed = _changed(out, img)
    hull = _rail_hull(ctx, severity, 2)
    import cv2
    hull = cv2.dilate(hull.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    assert changed.sum() > 200
    assert not (changed & ~hull).any(), f"{int((changed & ~hull).sum())} px changed outside the rail boxes"
    # the beam is opaque grey steel: at its centre line, 20 m ahead, the pixel is neutral grey
    d_rail, sign = rail_offsets(ctx, severity, np.random.default_rng(2))[0]
    pix = draw.project(ctx, draw.road_points(ctx, d_rail - sign * 0.15, 20.0, lift=0.62))[0]
    u, v = int(round(pix[0])), int(round(pix[1]))
    r, g, b = out[v, u].astype(int)
    assert changed[v, u] and max(r, g, b) - min(r, g, b) < 25


def test_guard_rail_area_grows_and_reaches_the_lane():
    img, ctx = _case(w=320, h=180)
    for seed in (0, 1, 2):
        area = [int(_changed(RENDERERS["guard_rail"](img, ctx, s, np.random.default_rng(seed)), img).sum())
                for s in range(1, 6)]
        assert all(a < b for a, b in zip(area, area[1:])), f"seed {seed}: {area}"
    # posts stand on the ground every post_spacing_m: one is drawn at 16 m (a multiple of 2 m)
    out = RENDERERS["guard_rail"](img, ctx, 5, np.random.default_rng(0))
    d_rail, sign = rail_offsets(ctx, 5, np.random.default_rng(0))[0]
    u, v = np.round(draw.project(ctx, draw.road_points(ctx, d_rail, 16.0, lift=0.3))[0]).astype(int)
    assert _changed(out, img)[v, u]
    # the beam runs next to the outermost lane line at level 5, far from it at level 1
    lanes = sorted(ctx.lane_offsets)
    line_d = lanes[-1] if sign > 0 else lanes[0]
    gap = []
    for s in (1, 5):
        d, sg = [r for r in rail_offsets(ctx, s, np.random.default_rng(0)) if r[1] == sign][0]
        beam = draw.project(ctx, draw.road_points(ctx, d - sg * 0.15, 20.0, lift=0.55))[0]
        line = draw.project(ctx, draw.road_points(ctx, line_d, 20.0))[0]
        gap.append(abs(beam[0] - line[0]))
    assert gap[1] < 0.3 * gap[0]
