"""Illusion.parameters(): bounds from the severity levels, points checked, a severity's point renders it exactly."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest

from lanevil_train.illusions import ILLUSIONS, context_from_scene
from lanevil_train.illusions.parameters import Parameter
from lanevil_train.sim import SceneParams, build_scene, render_scene

W, H = 160, 96
SCENES = {"day": (3, SceneParams()), "wet_night": (7, SceneParams(road="left_curve", weather="night"))}


@lru_cache(maxsize=None)
def _scene(key: str):
    seed, params = SCENES[key]
    image = render_scene(seed, params, W, H)["image"]
    image.setflags(write=False)
    return image, context_from_scene(build_scene(seed, params, W, H))


@pytest.mark.parametrize("name", sorted(ILLUSIONS))
def test_every_severity_point_renders_that_severity_byte_for_byte(name):
    illusion = ILLUSIONS[name]
    for key, seeds in (("day", (0, 7)), ("wet_night", (3,))):
        image, ctx = _scene(key)
        for severity in range(1, 6):
            for seed in seeds:
                expected = illusion(image, ctx, severity, seed)
                assert np.array_equal(illusion.render_point(image, ctx, illusion.point(severity), seed), expected), \
                    (key, severity, seed)


@pytest.mark.parametrize("name", sorted(ILLUSIONS))
def test_bounds_are_the_levels_range_and_contain_every_severity(name):
    illusion = ILLUSIONS[name]
    space = illusion.parameters()
    assert space.names == tuple(illusion.levels[0])
    for parameter in space:
        values = [level[parameter.name] for level in illusion.levels]
        assert (parameter.low, parameter.high) == (min(values), max(values))
        assert parameter.fixed == (len(set(values)) == 1)
        assert parameter.kind in ("int", "float")
        if parameter.kind == "int":
            assert all(isinstance(v, int) for v in values)
    for severity in range(1, 6):
        assert space.check(illusion.point(severity)) == illusion.levels[severity - 1]
    assert space.searched and all(not p.fixed for p in space.searched)


def test_kinds_units_and_fixed_parameters_of_a_few_illusions():
    fence = ILLUSIONS["fence_shadow"].parameters()
    assert fence["opacity"] == Parameter("opacity", "float", 0.25, 0.65, "")
    assert fence["sun_elevation_deg"] == Parameter("sun_elevation_deg", "float", 11, 50, "deg")
    wires = ILLUSIONS["wire_shadow"].parameters()
    assert wires["along_wire_count"] == Parameter("along_wire_count", "int", 1, 6, "")
    assert wires["wire_height_m"].fixed and wires["wire_height_m"].low == 7.0
    assert {p.name for p in wires.searched} == {"sun_elevation_deg", "sun_azimuth_deg", "opacity", "along_wire_count",
                                                "cross_wire_count", "shadow_width_m", "penumbra_px"}
    rail = ILLUSIONS["guard_rail"].parameters()
    assert rail["sides"].kind == "int" and rail["beam_height_m"].describe() == "beam_height_m (fixed at 0.7 m)"
    assert ILLUSIONS["vehicle"].parameters()["count"].describe() == "count (int in [1, 4])"


def test_a_point_is_typed_and_fixed_parameters_may_be_left_out():
    illusion = ILLUSIONS["wire_shadow"]
    point = illusion.point(4)
    for fixed in ("wire_height_m", "wire_spacing_m", "sag_m"):
        del point[fixed]
    point["along_wire_count"] = np.int64(4)
    checked = illusion.parameters().check(point)
    assert checked == illusion.levels[3] and type(checked["along_wire_count"]) is int
    assert type(checked["sun_elevation_deg"]) is float and list(checked) == list(illusion.levels[3])
    image, ctx = _scene("day")
    assert np.array_equal(illusion.render_point(image, ctx, point, 2), illusion(image, ctx, 4, 2))


@pytest.mark.parametrize("change, message", [
    ({"opacity": 0.9}, r"fence_shadow: parameter opacity = 0\.9 is outside its bounds: opacity has range "
                       r"\[0\.25, 0\.65\]"),
    ({"sun_elevation_deg": 5}, r"sun_elevation_deg = 5 is outside its bounds: .*\[11, 50\]"),
    ({"fence_length_m": float("nan")}, r"parameter fence_length_m must be finite"),
    ({"opacity": "0.5"}, r"parameter opacity must be a number, got '0\.5' \(expected opacity \(float in"),
    ({"puddle_m": 1.0}, r"fence_shadow has no parameter 'puddle_m'; it has: sun_elevation_deg, "),
])
def test_a_point_outside_the_space_is_refused_naming_the_parameter(change, message):
    illusion = ILLUSIONS["fence_shadow"]
    image, ctx = _scene("day")
    with pytest.raises(ValueError, match=message):
        illusion.render_point(image, ctx, {**illusion.point(3), **change})


def test_counts_must_be_whole_and_fixed_values_stay_fixed_and_nothing_may_be_missing():
    illusion = ILLUSIONS["wire_shadow"]
    space = illusion.parameters()
    with pytest.raises(ValueError, match=r"along_wire_count must be a whole number, got 2\.5 "
                                         r"\(expected along_wire_count \(int in \[1, 6\]\)\)"):
        space.check({**illusion.point(3), "along_wire_count": 2.5})
    with pytest.raises(ValueError, match=r"cross_wire_count must be a number, got True"):
        space.check({**illusion.point(3), "cross_wire_count": True})
    with pytest.raises(ValueError, match=r"wire_height_m = 8\.0 is outside its bounds: wire_height_m is fixed at 7"):
        space.check({**illusion.point(3), "wire_height_m": 8.0})
    point = illusion.point(3)
    del point["opacity"]
    with pytest.raises(ValueError, match=r"wire_shadow: the point has no value for opacity \(float in \[0\.3, 0\.7\]"):
        space.check(point)
    with pytest.raises(ValueError, match="a point is a dict of parameter values, got list"):
        space.check([0.5])
    with pytest.raises(KeyError, match="wire_shadow has no parameter 'puddle'"):
        space["puddle"]


def _between(illusion, a: int, b: int) -> dict:
    """The point halfway between severities a and b (an int parameter rounded down)."""
    space = illusion.parameters()
    return {p.name: (int if p.kind == "int" else float)((illusion.levels[a - 1][p.name]
                                                         + illusion.levels[b - 1][p.name]) / 2) for p in space}


@pytest.mark.parametrize("name", sorted(ILLUSIONS))
def test_a_point_between_two_severities_renders_between_them(name):
    illusion = ILLUSIONS[name]
    image, ctx = _scene("day")
    # the first neighbours whose middle is a point of its own (bicycle's 3 and 4 differ by one count only)
    a, b = next((a, a + 1) for a in (3, 4, 2, 1) if _between(illusion, a, a + 1) not in illusion.levels)
    middle = illusion.render_point(image, ctx, _between(illusion, a, b), 1)
    assert middle.shape == image.shape and middle.dtype == np.uint8
    for other in (image, illusion(image, ctx, a, 1), illusion(image, ctx, b, 1)):
        assert not np.array_equal(middle, other)
    centre = illusion.render_point(image, ctx, illusion.parameters().midpoint(), 1)
    assert not np.array_equal(centre, image)


def test_a_point_caps_where_items_are_placed_by_its_own_extent():
    # road_crack's z_far_m: every crack starts nearer than the point's z_far (the severities never cap it)
    illusion = ILLUSIONS["road_crack"]
    image, ctx = _scene("day")
    top = illusion.point(5)
    near = illusion.render_point(image, ctx, {**top, "z_far_m": 15.0}, 4)
    far = illusion.render_point(image, ctx, top, 4)
    rows_changed = [np.flatnonzero((out != image).any(axis=(1, 2))) for out in (near, far)]
    assert rows_changed[0].min() > rows_changed[1].min()  # nothing as far up the image (as far away)
