"""Every preset renders at small size with sensible brightness; bad params raise ValueError."""

import numpy as np
import pytest

from lanevil_train.sim import (
    MARKING_TYPES,
    ROAD_KINDS,
    SCENE_KIND_NAMES,
    WEATHER_NAMES,
    SceneParams,
    render_scene,
)

W, H = 160, 90


@pytest.mark.parametrize("weather", WEATHER_NAMES)
@pytest.mark.parametrize("kind", SCENE_KIND_NAMES)
def test_every_weather_and_scene_kind_renders(weather, kind):
    out = render_scene(1, SceneParams(weather=weather, scene_kind=kind), W, H)
    img = out["image"]
    assert img.shape == (H, W, 3) and img.dtype == np.uint8
    assert img.std() > 5  # not a blank frame
    assert out["meta"]["weather"] == weather and out["meta"]["scene_kind"] == kind
    assert len(out["lanes"]) >= 2


@pytest.mark.parametrize("road", ROAD_KINDS)
def test_every_road_kind_renders(road):
    out = render_scene(2, SceneParams(road=road), W, H)
    assert out["meta"]["road"] == road and len(out["lanes"]) == 4


@pytest.mark.parametrize("marking", MARKING_TYPES)
def test_every_marking_type_renders(marking):
    out = render_scene(3, SceneParams(num_lanes=2, markings=(marking,) * 3, paint_wear=0.0), W, H)
    assert out["meta"]["markings"] == [marking] * 3


def test_nine_marking_types():
    assert len(MARKING_TYPES) == 9


def _road_patch(img):
    return img[int(H * 0.8):, W // 3: 2 * W // 3].astype(float)


def test_sensible_brightness():
    means = {w: render_scene(4, SceneParams(weather=w), W, H)["image"].mean() for w in WEATHER_NAMES}
    assert means["night"] < 0.5 * means["clear_noon"]
    assert means["night"] < means["sunset"] < means["clear_noon"]
    # sunset light is warm: red over blue
    sunset = render_scene(4, SceneParams(weather="sunset"), W, H)["image"].astype(float)
    assert sunset[..., 0].mean() > sunset[..., 2].mean() + 15
    # wet asphalt is darker than dry asphalt (near the camera, same scene)
    dry = _road_patch(render_scene(4, SceneParams(weather="clear_noon", markings=("none",) * 4), W, H)["image"])
    wet = _road_patch(render_scene(4, SceneParams(weather="wet_noon", markings=("none",) * 4), W, H)["image"])
    assert wet.mean() < dry.mean() - 10
    # at night the lamps light pools on the road: the road has bright and dark stretches
    night = render_scene(4, SceneParams(weather="night", scene_kind="urban"), W, H)["image"].astype(float)
    road_rows = night[H // 2 + 5:].mean(axis=2)
    assert road_rows.max() > 3 * np.median(road_rows)


@pytest.mark.parametrize("field,kwargs", [
    ("weather", dict(weather="hail")),
    ("scene_kind", dict(scene_kind="desert")),
    ("road", dict(road="spiral")),
    ("num_lanes", dict(num_lanes=1)),
    ("num_lanes", dict(num_lanes=6)),
    ("markings", dict(num_lanes=2, markings=("white_solid",) * 4)),
    ("markings[1]", dict(num_lanes=2, markings=("white_solid", "pink_dashed", "white_solid"))),
    ("lane_width", dict(lane_width=10.0)),
    ("ego_lane", dict(num_lanes=2, ego_lane=2)),
    ("paint_wear", dict(paint_wear=-0.1)),
])
def test_bad_params_raise_value_error_naming_the_field(field, kwargs):
    with pytest.raises(ValueError, match=field.replace("[", r"\[").replace("]", r"\]")):
        SceneParams(**kwargs)


@pytest.mark.parametrize("w,h,name", [(0, 90, "width"), (160, -5, "height"), (160.5, 90, "width")])
def test_bad_size_raises(w, h, name):
    with pytest.raises(ValueError, match=name):
        render_scene(0, SceneParams(), w, h)


def test_meta_has_required_keys():
    meta = render_scene(5, None, W, H)["meta"]
    for key in ("seed", "road", "weather", "scene_kind", "num_lanes", "markings", "width", "height", "camera"):
        assert key in meta
    assert meta["camera"]["fx"] == pytest.approx(W / 2)  # 90 deg HFOV
    assert len(meta["markings"]) == len(render_scene(5, None, W, H)["lanes"])
