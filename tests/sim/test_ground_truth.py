"""Ground-truth lanes sit on painted pixels; half a lane away there is asphalt."""

import numpy as np
import pytest

from lanevil_train.lanes import lane_x_at
from lanevil_train.sim import SceneParams, build_scene, render_scene

W, H = 320, 180


def _pixels(img, pts):
    ij = np.round(pts).astype(int)
    return img[ij[:, 1], ij[:, 0]].astype(float)


def _near_half(lane):
    """The half of the lane nearest the camera (by image rows)."""
    return lane[lane[:, 1] >= (lane[:, 1].max() + lane[:, 1].min()) / 2]


def _on_rows(lane, scene, d, half_width, min_px=2.0):
    """GT points at integer rows (x interpolated there) where the painted stripe of half width
    half_width around offset d is at least min_px wide, so the rounded pixel lies inside it."""
    rows = np.arange(np.ceil(lane[:, 1].min()), np.floor(lane[:, 1].max()) + 1)
    x = lane_x_at(lane, rows)
    xl = lane_x_at(scene.lane_polyline(d - half_width), rows)
    xr = lane_x_at(scene.lane_polyline(d + half_width), rows)
    ok = (x >= 0) & (xl >= 0) & (xr >= 0) & (np.abs(xr - xl) >= min_px)
    return np.stack([x[ok], rows[ok]], axis=1)


@pytest.mark.parametrize("road", ["straight", "left_curve", "right_curve", "s_curve", "uphill", "downhill"])
def test_solid_white_gt_on_paint_and_asphalt_between(road):
    p = SceneParams(road=road, weather="clear_noon", scene_kind="highway", num_lanes=3, lane_width=3.6,
                    markings=("white_solid",) * 4, paint_wear=0.0, curvature=1 / 250, grade=0.08)
    out = render_scene(11, p, W, H)
    scene = build_scene(11, p, W, H)
    img = out["image"]
    assert len(out["lanes"]) == 4 and out["meta"]["markings"] == ["white_solid"] * 4
    for lane, d in zip(out["lanes"], out["meta"]["lane_offsets_m"]):
        on = _pixels(img, _on_rows(lane, scene, d, 0.075))
        assert len(on) >= 5
        assert on.mean(axis=1).min() > 170, f"{road} d={d}: GT not on white paint"
        if d < max(out["meta"]["lane_offsets_m"]):  # half a lane to the right: asphalt
            off = _pixels(img, _near_half(scene.lane_polyline(d + 1.8)))
            assert len(off) >= 5
            assert off.mean(axis=1).max() < 130, f"{road} d={d}: no asphalt between lanes"


def test_yellow_line_has_yellow_hue_and_double_line_gt_is_between_stripes():
    p = SceneParams(weather="clear_noon", scene_kind="urban", num_lanes=2, paint_wear=0.0,
                    markings=("yellow_solid", "white_solid", "yellow_double_solid"))
    out = render_scene(5, p, W, H)
    img = out["image"]
    scene = build_scene(5, p, W, H)
    d = out["meta"]["lane_offsets_m"]
    yel = _pixels(img, _on_rows(out["lanes"][0], scene, d[0], 0.075))
    assert len(yel) >= 5
    assert np.all(yel[:, 0] - yel[:, 2] > 60) and np.all(yel[:, 1] - yel[:, 2] > 40)
    # the GT of a double line is the middle of the 0.12 m gap between its two 0.12 m stripes
    centre = _pixels(img, _on_rows(out["lanes"][2], scene, d[2], 0.06))
    stripe = _pixels(img, _on_rows(scene.lane_polyline(d[2] + 0.12), scene, d[2] + 0.12, 0.06))
    assert len(centre) >= 3 and len(stripe) >= 5
    assert stripe.mean(axis=1).min() > 140 and centre.mean(axis=1).max() < 110


def test_dashed_gt_is_continuous_and_on_paint_at_painted_dashes():
    p = SceneParams(weather="clear_noon", scene_kind="highway", num_lanes=2, paint_wear=0.0,
                    markings=("white_solid", "white_dashed", "white_solid"), travel=0.0)
    w, h = 640, 360
    out = render_scene(9, p, w, h)
    scene = build_scene(9, p, w, h)
    lane = out["lanes"][1]
    assert out["meta"]["markings"][1] == "white_dashed"
    assert np.all(np.diff(lane[:, 1]) < 0) and np.max(-np.diff(lane[:, 1])) <= 1.0 + 1e-9  # dense, continuous
    pts = _on_rows(lane, scene, 0.0, 0.075)
    ground = scene.ground_hit(pts[:, 0], pts[:, 1])
    s = scene.road.arc_length(ground[:, 2]) - out["meta"]["dash_phase_m"]
    period = p.dash_length + p.dash_gap
    q = np.mod(s, period)
    painted = (q > 0.4) & (q < p.dash_length - 0.4)
    gap = (q > p.dash_length + 0.6) & (q < period - 0.6)
    assert painted.sum() >= 3 and gap.sum() >= 3
    bright = _pixels(out["image"], pts).mean(axis=1)
    assert bright[painted].min() > 170
    assert bright[gap].max() < 130


def test_lanes_are_ordered_left_to_right_and_y_descending():
    out = render_scene(4, SceneParams(num_lanes=5, road="right_curve"), W, H)
    lanes = out["lanes"]
    assert len(lanes) == 6
    for lane in lanes:
        assert lane.shape[1] == 2 and np.all(np.diff(lane[:, 1]) < 0)
        assert lane[:, 0].min() >= 0 and lane[:, 0].max() <= W - 1 and lane[:, 1].max() <= H - 1
    row = H * 0.56
    xs = [np.interp(row, lane[::-1, 1], lane[::-1, 0]) for lane in lanes if lane[:, 1].min() <= row <= lane[:, 1].max()]
    assert len(xs) == 6 and np.all(np.diff(xs) > 0)


def test_unpainted_boundary_is_not_gt():
    p = SceneParams(num_lanes=2, markings=("none", "white_dashed", "white_solid"))
    out = render_scene(2, p, W, H)
    assert len(out["lanes"]) == 2 and out["meta"]["markings"] == ["white_dashed", "white_solid"]
