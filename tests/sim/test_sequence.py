"""sim.sequence: a camera driving along the road (re-expanded geometry, reference <-> moved mapping)."""

from __future__ import annotations

import numpy as np
import pytest

from lanevil_train.sim import SceneParams, build_scene, shade_scene
from lanevil_train.sim.sequence import FrameView, PoseCamera, road_at, scene_at, z_at_arc_length

W, H = 320, 180


def _scene(**kw):
    return build_scene(7, SceneParams(**kw), W, H)


def _slope_of(road, z):
    """dh/dz of the road profile at z (finite difference)."""
    return (road.height(z + 1e-4) - road.height(z - 1e-4)) / 2e-4


@pytest.mark.parametrize("s0", [-15.0, 5.0, 30.0, 45.0, 70.0, 120.0])
def test_vertical_profile_seen_from_a_pose_is_the_road_relative_to_the_pitched_camera(s0):
    road = _scene(road="uphill", grade=0.08, slope_start=20.0).road
    moved = road_at(road, s0)
    t = np.linspace(0.0, 90.0, 31)
    h0 = road.height(np.float64(s0))
    expected = road.height(s0 + t) - h0 - _slope_of(road, np.float64(s0)) * t
    np.testing.assert_allclose(moved.height(t), expected, atol=1e-6)


@pytest.mark.parametrize("kind", ["s_curve", "right_curve", "downhill", "straight"])
def test_moving_twice_is_moving_once(kind):
    road = _scene(road=kind, curvature=1 / 250, s_curve_flip=40.0, slope_start=15.0).road
    a = road_at(road_at(road, 12.0), 23.0)
    b = road_at(road, 35.0)
    for name in ("x0", "k", "j", "grade", "slope_start", "slope_length"):
        assert getattr(a, name) == pytest.approx(getattr(b, name), abs=1e-9), name


def test_curvature_follows_the_road_and_the_lateral_offset_is_kept():
    road = _scene(road="s_curve", curvature=1 / 200, s_curve_flip=40.0).road
    assert road_at(road, 0.0) == road
    assert road_at(road, 40.0).k == pytest.approx(0.0, abs=1e-12)  # the flip point
    assert road_at(road, 80.0).k == pytest.approx(-1 / 200)
    assert road_at(road, 80.0).x0 == road.x0


def test_arc_length_inverse_works_behind_the_camera_too():
    road = _scene(road="s_curve", curvature=1 / 200, s_curve_flip=40.0).road
    s = np.array([-40.0, -3.0, 0.0, 7.5, 60.0, 150.0])
    np.testing.assert_allclose(road.arc_length(z_at_arc_length(road, s)), s, atol=1e-9)


@pytest.mark.parametrize("kind", ["s_curve", "uphill", "left_curve"])
def test_frame_view_maps_road_points_by_arc_length_and_back(kind):
    scene = _scene(road=kind, curvature=1 / 220, s_curve_flip=45.0, grade=0.07, slope_start=15.0)
    view = FrameView.at(scene, 27.0)
    s = np.array([30.0, 40.0, 60.0, 80.0])
    d = np.array([-3.0, 0.0, 1.5, 4.0])
    ref = scene.road_point(s, d) + np.array([0.0, 1.2, 0.0])  # 1.2 m above the road
    cur = view.to_current(ref)
    expected = view.current.road_point(s - 27.0, d) + np.array([0.0, 1.2, 0.0])
    np.testing.assert_allclose(cur, expected, atol=1e-6)
    np.testing.assert_allclose(view.to_reference(cur), ref, atol=1e-6)


def test_pose_camera_projects_reference_points_from_the_moved_pose():
    scene = _scene(road="right_curve", curvature=1 / 200)
    view = FrameView.at(scene, 18.0)
    cam = PoseCamera.of(view)
    pts = scene.road_point(np.array([25.0, 40.0]), np.array([0.5, -2.0]))
    np.testing.assert_allclose(cam.project(pts), view.camera.project(view.to_current(pts)))
    # the moved camera stands 18 m along the centre line, at the camera's own lateral offset, 1.5 m up
    s, d = scene.road_coords(cam.position[0], cam.position[2])
    assert float(s) == pytest.approx(18.0, abs=1e-6)
    assert float(d) == pytest.approx(float(scene.road.lateral(0.0, 0.0)), abs=1e-6)
    # ground_intersect is the inverse of project on the road
    pix = cam.project(pts)
    np.testing.assert_allclose(cam.ground_intersect(pix[:, 0], pix[:, 1]), pts, atol=1e-4)


def _x_at_row(scene, d, row):
    """Image x where the GT polyline of the road line at offset d crosses image row `row`."""
    line = scene.lane_polyline(d)
    return float(np.interp(row, line[::-1, 1], line[::-1, 0]))


def _bend_px(scene, d, ahead=60.0):
    """How far right (px) of the image centre the road line at offset d lies `ahead` metres on."""
    return float(scene.camera.project(scene.road.world_point(d, ahead))[0] - scene.camera.cx)


def test_camera_follows_a_curve_the_ego_lane_stays_centred_at_the_bottom():
    scene = _scene(road="right_curve", curvature=1 / 150, num_lanes=3, ego_lane=1)
    ego_left, ego_right = (scene.road.boundaries[i].d for i in (1, 2))
    d_cam = float(scene.road.lateral(0.0, 0.0))
    centres = []
    for s0 in (0.0, 25.0, 50.0, 75.0):
        frame = scene_at(scene, s0)
        centres.append((_x_at_row(frame, ego_left, H - 5) + _x_at_row(frame, ego_right, H - 5)) / 2.0)
        # (12 m right at 60 m: 32 px) the road still bends right ahead of every frame
        assert _bend_px(frame, d_cam) > 25
    assert abs(centres[0] - W / 2) < 20  # the ego lane is centred at the bottom ...
    assert np.ptp(centres) < 1.0  # ... in every frame: the camera drives in its lane, not off the road


def test_camera_follows_an_s_curve_the_far_bend_changes_side():
    scene = _scene(road="s_curve", curvature=1 / 200, s_curve_flip=40.0, num_lanes=2, ego_lane=0)
    d_cam = float(scene.road.lateral(0.0, 0.0))
    bends = [_bend_px(scene_at(scene, s0), d_cam, ahead=30.0) for s0 in (0.0, 40.0, 80.0)]
    assert bends[0] > 5 and bends[2] < -5  # ahead it bends right at the start, left past the flip
    assert bends[0] > bends[1] > bends[2]
    assert _x_at_row(scene_at(scene, 80.0), d_cam, H - 5) == pytest.approx(_x_at_row(scene, d_cam, H - 5), abs=3.0)


def test_camera_follows_a_slope():
    uphill = _scene(road="uphill", grade=0.09, slope_start=20.0)
    flat = _scene(road="straight")
    d = float(uphill.road.lateral(0.0, 0.0))
    top_flat = flat.lane_polyline(d)[-1, 1]
    top_before = uphill.lane_polyline(d)[-1, 1]
    top_past = scene_at(uphill, 80.0).lane_polyline(d)[-1, 1]  # on the grade: pitched with it, looks flat
    assert top_before < top_flat - 5  # the rise ahead climbs up the image
    assert top_past == pytest.approx(top_flat, abs=0.5)


def test_moved_frame_renders_deterministically_and_differs_from_the_reference():
    scene = _scene(road="left_curve")
    a, b = shade_scene(scene_at(scene, 6.0)), shade_scene(scene_at(scene, 6.0))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, shade_scene(scene))


def test_bad_pose_is_refused():
    with pytest.raises(ValueError, match="s0"):
        road_at(_scene().road, float("nan"))


def _paint_column(image, row, near_x, half_window=25):
    """Centre (px) of the brightest run of pixels of `row` within half_window px of near_x: the paint there."""
    lo = max(0, int(near_x) - half_window)
    values = image[row, lo:int(near_x) + half_window].astype(np.float64).sum(axis=1)
    bright = np.flatnonzero(values > values.max() - 60)
    return lo + float(bright.mean())


def test_a_cars_lateral_offset_and_heading_move_the_lanes_as_the_camera_model_predicts():
    scene = build_scene(7, SceneParams(road="straight", markings=("white_solid",) * 4, paint_wear=0.0,
                                       weather="clear_noon", pitch_deg=2.0, yaw_deg=0.0), 640, 360)
    centre = -scene.road.x0
    right = scene.road.boundaries[2].d  # the ego lane's right line
    row = 300
    z = float(scene.camera.ground_intersect(np.array([320.0]), np.array([float(row)]))[0, 2])
    base = scene_at(scene, 0.0, centre, 0.0)
    moved = scene_at(scene, 0.0, centre + 0.5, 0.0)  # the car 0.5 m further right: the line 0.5 m nearer
    x_base, x_moved = _x_at_row(base, right, row), _x_at_row(moved, right, row)
    fx = scene.camera.fx
    # the line's image x at depth z is cx + fx * (lateral distance to it) / (depth along the optical axis)
    depth = float(base.camera.to_camera(np.array([[right - centre, 0.0, z]]))[0, 2])
    assert x_base - x_moved == pytest.approx(fx * 0.5 / depth, rel=0.02)
    # the image itself: the painted line is where the ground truth says, in both views
    for view, x in ((base, x_base), (moved, x_moved)):
        assert _paint_column(shade_scene(view), row, x) == pytest.approx(x, abs=1.5)
    # a heading of +2 degrees (turned right) moves the far road left by fx * tan(2 deg)
    turned = scene_at(scene, 0.0, centre, np.radians(2.0))
    far = 1000.0
    shift = (scene.camera.project(base.road.world_point(centre, far))[0]
             - turned.camera.project(turned.road.world_point(centre, far))[0])
    assert shift == pytest.approx(fx * np.tan(np.radians(2.0)), rel=0.01)
    with pytest.raises(ValueError, match="heading"):
        scene_at(scene, 0.0, centre, np.radians(45.0))
